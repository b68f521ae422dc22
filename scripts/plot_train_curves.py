"""The README's loss-curve figure: train and validation loss of the four stages' runs, one panel each.

    python scripts/plot_train_curves.py runs docs/train_loss_curves.png [--title "..."]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sceneforge.learn.train import draw_losses, read_config, read_metrics

PANELS = (("depth", "depth (masked Huber, eq. 1)"), ("seg", "segmentation (cross-entropy, 2 layers)"),
          ("overhead", "overhead (L1 height + cross-entropy)"), ("camera", "camera proposal (L1 on tx, ty, sigma)"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", help="folder holding the runs depth/, seg/, overhead/, camera/")
    parser.add_argument("out", help="PNG to write")
    parser.add_argument("--title", default=None)
    args = parser.parse_args()
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10.8, 6.3))
    for k, (stage, label) in enumerate(PANELS):
        ax = fig.add_subplot(2, 2, k + 1)
        run = Path(args.runs) / stage
        if not (run / "metrics.csv").exists():
            ax.set_title(f"{label}: no run")
            continue
        draw_losses(ax, read_metrics(run / "metrics.csv"))
        config = read_config(run)
        ax.set_title(f"{label}, {config.epochs} epochs", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    if args.title:
        fig.suptitle(args.title, fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(args.out)


if __name__ == "__main__":
    main()
