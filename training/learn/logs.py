"""A stage's logs: ``log.csv`` (one row per logged step and split; trimmed back to the checkpoint on resuming),
TensorBoard's ``tb/`` and ``loss.png``."""

from __future__ import annotations

import csv
from pathlib import Path

from genre_backend.atomic import atomic_write, atomic_write_bytes

__all__ = ["LOG_FIELDS", "trim_log", "plot_losses"]


LOG_FIELDS = ["step", "split", "loss", "terms", "lr", "s_per_step", "samples_per_s"]  # log.csv's columns


def trim_log(csv_path: Path, step: int) -> bool:
    """Keep only ``log.csv``'s rows up to ``step`` (the checkpoint a run resumes from); atomically.

    A run killed between two checkpoints has logged steps past the last one;
    the resumed run logs them again, so without this they would appear twice.
    Rows up to ``step`` were all written (and flushed) before that checkpoint
    was saved.  A last line without its newline (a kill mid-write) is dropped
    too.  Returns False when there is no usable log (no file, or another
    header): the caller then starts a new one.
    """
    try:
        text = csv_path.read_bytes().decode("utf-8", "surrogateescape")
    except FileNotFoundError:
        return False
    parts = text.split("\n")  # the csv module ends rows with \r\n: kept as they are
    lines = [p + "\n" for p in parts[:-1]] + ([parts[-1]] if parts[-1] else [])
    header = ",".join(LOG_FIELDS) + "\n"
    if not lines or lines[0].replace("\r\n", "\n") != header:
        return False
    kept = [lines[0]]
    for line in lines[1:]:
        if not line.endswith("\n"):
            break  # cut off by the kill: nothing after it was written
        row = next(csv.reader([line]), [])
        if len(row) == len(LOG_FIELDS) and row[0].isdigit() and int(row[0]) <= step:
            kept.append(line)
    if len(kept) < len(lines):
        atomic_write_bytes(csv_path, "".join(kept).encode("utf-8", "surrogateescape"))
    return True


def plot_losses(csv_path: Path, png_path: Path, stage: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(csv_path.open()))
    if not rows:
        return
    fig, ax = plt.subplots(figsize=(7, 4))
    for split, style in (("train", "-"), ("val", "o-")):
        pts = [(int(r["step"]), float(r["loss"])) for r in rows if r["split"] == split]
        if pts:
            ax.plot(*zip(*pts), style, label=split, markersize=3)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(f"GenRe training: {stage} stage")
    ax.legend()
    fig.tight_layout()
    atomic_write(png_path, lambda fh: fig.savefig(fh, format="png", dpi=90))
    plt.close(fig)
