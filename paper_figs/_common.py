"""Shared by the figure scripts: the output folder, the lesson's cube, and one writer for a
figure's PNG, its numbers (CSV) and its caption (the lesson's claim beside the measured
value, recomputed by the script).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).resolve().parent
OUT = HERE / "out"
DATA = Path(os.environ.get("JAXREG_DATA", HERE.parents[1] / "shared" / "data"))


def save(fig, name: str, header: list[str], rows, caption: str) -> None:
    """Writes ``out/<name>.png``, ``out/<name>.csv`` (``header`` + ``rows``) and
    ``out/<name>.txt`` (the caption), and prints the caption."""
    OUT.mkdir(exist_ok=True)
    fig.savefig(OUT / f"{name}.png", dpi=110)
    plt.close(fig)
    with open(OUT / f"{name}.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for row in rows:
            writer.writerow([f"{v:.6g}" if isinstance(v, float) else v for v in row])
    (OUT / f"{name}.txt").write_text(caption.strip() + "\n")
    print(f"{name}: {caption.strip()}\n  wrote {OUT / name}.png/.csv/.txt")
