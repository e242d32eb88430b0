"""Shared output of the report CLIs: OUT/<stem>.json (rows) and OUT/<stem>.md (a table)."""
from __future__ import annotations

import json
import os


def write(out_dir: str, stem: str, rows: list, table: str) -> None:
  """Writes both files and prints the table."""
  os.makedirs(out_dir, exist_ok=True)
  with open(os.path.join(out_dir, f"{stem}.json"), "w") as f:
    json.dump(rows, f, indent=2)
  with open(os.path.join(out_dir, f"{stem}.md"), "w") as f:
    f.write(table)
  print(table)
  print(f"wrote {out_dir}/{stem}.json, {stem}.md")
