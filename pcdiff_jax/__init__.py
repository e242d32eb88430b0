"""pcdiff_jax: proposal-conditioned latent diffusion for closed-loop traffic simulation."""
from pcdiff_jax.shipped import pretrained

__version__ = "0.1.0"
