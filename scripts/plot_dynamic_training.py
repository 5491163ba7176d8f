"""Quality against training time of ``train-dynamic`` runs (issue 28): one curve per model directory.

Each model directory's ``metrics.json`` holds the training log (every 100 iterations: the mean
PSNR of the last 100 training frames against their ground truth, and the seconds of training so
far) and the final test PSNR (mean over the scene's test frames, each rendered at its own time).
The plot draws the training curves, marks each run's final test PSNR at its training time, and
draws the 30 dB bar and the 45-minute budget. The same points go to a CSV.

    python scripts/plot_dynamic_training.py ../outputs/dynamic_s7/jumpingjacks ../outputs/dynamic_s7/mutant \\
        ../outputs/dynamic_s7/standup --png dynamic_training.png --csv dynamic_training.csv
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

BAR_DB = 30.0
BUDGET_S = 45 * 60


def read_run(model_dir: Path) -> dict:
    """The training curve and final test result of one ``train-dynamic`` output folder."""
    metrics = json.loads((model_dir / "metrics.json").read_text())
    curve = [(row["it"], row["elapsed"], row["psnr"]) for row in metrics["log"]]
    test = metrics.get("test") or {}
    return {
        "scene": metrics["capture"],
        "curve": curve,
        "iterations": metrics["iterations_done"],
        "train_seconds": metrics["train_seconds"],
        "test_psnr": test.get("mean_psnr"),
        "test_ssim": test.get("mean_ssim"),
    }


def write_csv(runs: list[dict], path: Path) -> None:
    """One row per logged point; the final test result as a row with ``kind`` = test."""
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["scene", "kind", "iteration", "train_seconds", "psnr_db"])
        for run in runs:
            for iteration, seconds, value in run["curve"]:
                writer.writerow([run["scene"], "train_mean_100", iteration, f"{seconds:.1f}", f"{value:.3f}"])
            if run["test_psnr"] is not None:
                writer.writerow([run["scene"], "test", run["iterations"], f"{run['train_seconds']:.1f}",
                                 f"{run['test_psnr']:.3f}"])


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for run in runs:
        minutes = [seconds / 60 for _, seconds, _ in run["curve"]]
        line, = ax.plot(minutes, [value for *_, value in run["curve"]], lw=1.2,
                        label=f"{run['scene']} ({run['iterations']} it): training frames, mean of 100 iterations")
        if run["test_psnr"] is not None:
            ax.plot(run["train_seconds"] / 60, run["test_psnr"], "o", color=line.get_color(), ms=7,
                    label=f"{run['scene']} ({run['iterations']} it): test frames {run['test_psnr']:.2f} dB")
    ax.axhline(BAR_DB, color="k", ls="--", lw=0.8)
    ax.axvline(BUDGET_S / 60, color="grey", ls=":", lw=0.8)
    ax.set_xlabel("training time (minutes, 2-core CPU)")
    ax.set_ylabel("PSNR (dB) against ground truth")
    ax.set_title("train-dynamic at 400x400: quality against time")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", type=Path, help="train-dynamic output folders")
    parser.add_argument("--png", type=Path, required=True)
    parser.add_argument("--csv", type=Path)
    args = parser.parse_args()
    runs = [read_run(model_dir) for model_dir in args.models]
    plot(runs, args.png)
    if args.csv:
        write_csv(runs, args.csv)
    for run in runs:
        print(f"{run['scene']}: {run['iterations']} iterations, {run['train_seconds']:.0f} s, "
              f"test {run['test_psnr']:.2f} dB / SSIM {run['test_ssim']:.4f}")


if __name__ == "__main__":
    main()
