"""The large coverage run behind docs/statistics/coverage.csv and coverage.png (docs/diagnosis.md):

    python docs/statistics/coverage.py --n_sim=2000

Every method on the same synthetic lever experiments (`lerobot_condground.evaluation.coverage`): the
published levers' design (2 runs an arm, 3 checkpoints, 50 layouts, run spread as `levers_checkpoints.csv`
shows), then the same at other run spreads (`coverage_by_run_sd.csv`).
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_condground.evaluation.coverage import METHODS, Design, coverage  # noqa: E402

HERE = Path(__file__).parent


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--n_sim", type=int, default=2000)
    parser.add_argument("--run_sds", default="0.0,0.15,0.3,0.45,0.6")
    parser.add_argument("--out", type=Path, default=HERE)
    args = parser.parse_args()
    rows = []
    for run_sd in tqdm([float(s) for s in args.run_sds.split(",")], desc="run spreads"):
        table = coverage(Design(effect=0.5, run_sd=run_sd), Design(run_sd=run_sd), n_sim=args.n_sim, seed=0)
        rows.append(table.assign(run_sd=run_sd))
    table = pd.concat(rows, ignore_index=True)
    table.to_csv(args.out / "coverage_by_run_sd.csv", index=False, float_format="%.4f")
    published = table[table.run_sd == Design().run_sd]
    published[["method", "coverage", "false_positive_rate", "n_sim"]].to_csv(
        args.out / "coverage.csv", index=False, float_format="%.4f"
    )
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for method in METHODS:
        rows = table[table.method == method]
        axes[0].plot(rows.run_sd, rows.coverage, marker="o", label=method)
        axes[1].plot(rows.run_sd, rows.false_positive_rate, marker="o", label=method)
    axes[0].axhline(0.93, color="grey", ls="--", lw=1)
    axes[1].axhline(0.06, color="grey", ls="--", lw=1)
    for ax, title in zip(
        axes, ("coverage of the true difference", "false positives at α = 0.05"), strict=True
    ):
        ax.axvline(Design().run_sd, color="grey", ls=":", lw=1)
        ax.set(xlabel="run-to-run sd (logit)", title=title)
    axes[0].legend(fontsize=7)
    fig.suptitle(
        f"{args.n_sim} synthetic lever experiments per point (2 runs an arm, 3 checkpoints, 50 layouts)"
    )
    fig.tight_layout()
    fig.savefig(args.out / "coverage.png", dpi=120)


if __name__ == "__main__":
    main()
