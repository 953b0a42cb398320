"""Benchmarks of mpm_monitor (not unit tests): run as ``python -m bench.<module>``, see bench/README.md."""

import json
from pathlib import Path


def write_json(path, result, default=float) -> None:
    """Write a benchmark result as indented JSON (creating the folder) and say where."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1, default=default) + "\n", encoding="utf-8")
    print(f"wrote {path}")
