"""The training figure of docs/learning.md: for each stage's run, its train and validation loss (top)
and its validation metric (bottom: D1-D4 abs-rel, segmentation mIoU, overhead height L1
above 5 cm, camera loss), one column per stage that has a run.

    python scripts/plot_train_curves.py RUNS OUT.png [--title "..."]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sceneforge.learn.train import draw_losses, read_config, read_metrics

PANELS = (("depth", "depth (masked Huber, eq. 1)"), ("seg", "segmentation (cross-entropy, 2 layers)"),
          ("overhead", "overhead (L1 height + cross-entropy)"), ("camera", "camera proposal (L1 on tx, ty, sigma)"))
#: the validation metric drawn under each stage's losses: label, columns averaged
METRICS = {"depth": ("val abs-rel, mean of D1-D4", ("d1_absrel", "d2_absrel", "d3_absrel", "d4_absrel")),
           "seg": ("val mIoU (layers 1, 3)", ("seg_miou",)),
           "overhead": ("val height L1 above 5 cm (m)", ("height_l1_above_5cm",)),
           "camera": ("val loss (m)", ("loss",))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", help="folder holding the runs depth/, seg/, overhead/, camera/ (any of them)")
    parser.add_argument("out", help="PNG to write")
    parser.add_argument("--title", default=None)
    args = parser.parse_args()
    from matplotlib.figure import Figure

    panels = [(stage, label) for stage, label in PANELS if (Path(args.runs) / stage / "metrics.csv").exists()]
    if not panels:
        raise SystemExit(f"error: no run with a metrics.csv in {args.runs}")
    fig = Figure(figsize=(3.9 * len(panels), 6.6))
    for k, (stage, label) in enumerate(panels):
        run = Path(args.runs) / stage
        rows = read_metrics(run / "metrics.csv")
        ax = fig.add_subplot(2, len(panels), k + 1)
        draw_losses(ax, rows)
        config = read_config(run)
        ax.set_title(f"{label}\n{config.epochs} epochs of batch {config.batch_size}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        what, columns = METRICS[stage]
        val = [r for r in rows if r["split"] == "val" and all(r.get(c) not in (None, "") for c in columns)]
        ax = fig.add_subplot(2, len(panels), len(panels) + k + 1)
        ax.plot([int(r["step"]) for r in val], [sum(float(r[c]) for c in columns) / len(columns) for r in val],
                "o-", color="tab:green", markersize=4)
        ax.set_xlabel("step")
        ax.set_title(what, fontsize=9)
        ax.grid(True, alpha=0.3)
    if args.title:
        fig.suptitle(args.title, fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(args.out)


if __name__ == "__main__":
    main()
