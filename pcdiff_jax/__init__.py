"""pcdiff_jax: proposal-conditioned latent diffusion for closed-loop traffic simulation."""
__version__ = "0.1.0"
