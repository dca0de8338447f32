"""The README's and the documentation's teaser: a fit on the built-in problem, as a picture.

    python -m scripts.examples.teaser [--out docs/img/teaser.png] [--render 512] [--map 256]

Fits the built-in problem as ``jaxnm fit`` does (two views under six lights, 15 texel-space
Levenberg–Marquardt steps of 20 conjugate-gradient iterations, from a flat map) and draws
three panels: one of the target images, the fitted normal map, and the per-texel angular
error against the true map (texels that no view sees in grey). Needs matplotlib (the
``cli`` or ``notebook`` extra).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import jaxnm
from jaxnm import fit
from jaxnm.textures import linear_to_srgb
from scripts._cli import output, run_script

ROOT = Path(__file__).resolve().parents[2]
ERROR_MAX_DEG = 5.0


def make(render_size: int = 512, map_size: int = 256, steps: int = 15) -> dict:
    """Fit the built-in problem (``steps`` LM steps); returns the panels' arrays and the mean
    error."""
    problem, truth, _ = jaxnm.default_problem(render_size=render_size, map_size=map_size)
    prepared = fit.prepare(problem)
    result = fit.fit_normal_map(problem, fit.FitOptions(max_steps=steps, lsmr_steps=20),
                                ground_truth=truth, prepared=prepared, progress=False)
    seen = fit.seen_texels(prepared, (map_size, map_size))
    error = fit.angular_error(result.normals, truth)
    target = np.clip(np.asarray(linear_to_srgb(np.clip(problem.targets[0].image, 0, 1))), 0, 1)
    return {"target": target, "normals": np.asarray(result.normals), "error": error,
            "seen": seen, "mean_error": float(error[seen].mean())}


def draw(panels: dict, path: Path) -> None:
    """The three panels side by side, as a PNG."""
    import matplotlib
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10.2, 3.7), dpi=100)
    axes = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1, 1, 1.12]})
    error = np.ma.masked_array(panels["error"], ~panels["seen"])
    cmap = matplotlib.colormaps["inferno"].with_extremes(bad="0.6")
    axes[0].imshow(panels["target"])
    axes[0].set_title("target (1 of 12 images)", fontsize=10)
    axes[1].imshow(0.5 * panels["normals"] + 0.5, origin="upper")
    axes[1].set_title("fitted normal map", fontsize=10)
    im = axes[2].imshow(error, cmap=cmap, vmin=0.0, vmax=ERROR_MAX_DEG)
    axes[2].set_title(f"angular error (mean {panels['mean_error']:.2f}°)", fontsize=10)
    fig.colorbar(im, ax=axes[2], fraction=0.046, pad=0.03, label="degrees")
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "teaser.png")
    ap.add_argument("--render", type=int, default=512, help="target size (square)")
    ap.add_argument("--map", type=int, default=256, help="normal map size (square)")
    args = ap.parse_args(argv)
    output("--out", args.out, folder=False)  # before the work
    panels = make(args.render, args.map)
    draw(panels, args.out)
    print(f"wrote {args.out} (mean error {panels['mean_error']:.3f} deg over "
          f"{int(panels['seen'].sum())} seen texels)")


if __name__ == "__main__":
    sys.exit(run_script(main))
