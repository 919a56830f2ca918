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
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxreg as jr  # noqa: E402

HERE = Path(__file__).resolve().parent
OUT = HERE / "out"
DATA = Path(os.environ.get("JAXREG_DATA", HERE.parents[1] / "shared" / "data"))


def lesson_cube(angle_deg: float = 15.0, n: int = 800, seed: int = 0):
    """The lesson's experiment: ``n`` points uniform in a 6 cm cube (model), the scene turned
    ``angle_deg`` about z and shifted by (10, -20, 5) mm, with 2 mm Gaussian noise.
    Returns ``(model, scene, truth)``, float32 clouds and the model -> scene ``SE3``."""
    rng = np.random.default_rng(seed)
    model = rng.uniform(-0.03, 0.03, (n, 3)).astype(np.float32)
    truth = jr.SE3.from_rotation_and_translation(
        jr.SO3.from_z_radians(np.deg2rad(angle_deg)), jnp.array([0.01, -0.02, 0.005])
    )
    scene = np.asarray(truth @ model) + rng.normal(0.0, 0.002, model.shape)
    return model, scene.astype(np.float32), truth


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
