"""What ``genre eval`` writes for people: the Markdown table and the CSV files (atomically)."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path


from genre_backend.atomic import atomic_write, atomic_write_text

from .protocol import FLOOR, GROUPS, GROUP_LABEL, POINTS_LARGE, POINTS_SMALL, REPRESENTATION, threshold_key

__all__ = ['flatness_table', 'format_table', 'pyplot', 'save_figure', 'write_csv']


def write_csv(path: Path, rows: list[dict], columns: list[str] | None = None) -> None:
    """Write ``rows`` atomically (temporary file, then rename); floats with 6 significant digits.

    Without ``columns`` the first row's keys are the header and no rows means no file.
    """
    if not rows and columns is None:
        return
    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=columns or list(rows[0]))
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    atomic_write_text(path, buf.getvalue())


def _fmt(v: float, half: float | None = None) -> str:
    if v is None or not math.isfinite(v):
        return "–"
    return f"{v:.3f}" if half is None or not math.isfinite(half) else f"{v:.3f} ± {half:.3f}"


def format_table(per_class: list[dict], groups: dict, choice: dict, rows: list[str], header: str = "") -> str:
    """The Markdown report: group means (both threshold modes), then per group a per-class table."""
    rows = list(rows) + [FLOOR]
    present = [g for g in GROUPS if any(g in c["groups"].split("|") for c in per_class)]
    lines = [header] if header else []
    lines += [
        "Chamfer distance (CD): sum of the two mean nearest-neighbour distances (not squared), "
        f"{POINTS_SMALL:,} points per shape (CD10k: {POINTS_LARGE:,}), each cloud centred on its bounding box and scaled "
        "to a longest side of 1, in the view frame. F@1%/F@2%: F-score at 0.01/0.02 of that size (10,000 points). "
        "Lower CD is better; the noise floor is the truth against itself resampled. "
        f"*Seen t*: one threshold per row chosen on seen-test views only ({choice['source']}), applied everywhere. "
        f"*Best t/class*: the best of {min(choice['thresholds']):.2f}–{max(choice['thresholds']):.2f} per class (the paper's protocol). "
        "Class means weigh shapes equally; ± is the 95 % t-interval over shapes; group means are means of class means.",
        "",
        "## Group means (CD, 1,024 points)",
        "",
        "| method | seen t* | " + " | ".join(f"{GROUP_LABEL[g]} (seen t*)" for g in present) + " | " + " | ".join(f"{GROUP_LABEL[g]} (best t/class)" for g in present) + " |",
        "|---|---|" + "---|" * (2 * len(present)),
    ]
    for row in rows:
        t = "–" if row in (FLOOR, "Nearest training shape") else f"{choice['seen'].get(row, math.nan):.2f}"
        cells = [_fmt(groups["seen"][g].get(row, math.nan)) for g in present] + [_fmt(groups["per_class"][g].get(row, math.nan)) for g in present]
        lines.append(f"| {row} | {t} | " + " | ".join(cells) + " |")
    def ratio(a: str, b: str, g: str) -> str:
        num, den = groups["seen"][g].get(a, math.nan), groups["seen"][g].get(b, math.nan)
        return f"{num / den:.3f}" if math.isfinite(num) and math.isfinite(den) and den > 0 else "–"

    ratios = [(a, b) for a, b in ((REPRESENTATION, FLOOR), ("GenRe", "3D Completion"),
                                          ("GenRe-Oracle", "3D Completion-Oracle"), ("GenRe", "Nearest training shape")) if a in rows and b in rows]
    if ratios:
        lines += ["", "Ratios of group means (seen t*): " + "; ".join(
            f"{a} ÷ {b}: " + ", ".join(f"{GROUP_LABEL[g]} {ratio(a, b, g)}" for g in present) for a, b in ratios) + "."]
    for g in present:
        classes = sorted({c["class"] for c in per_class if g in c["groups"].split("|")})
        lines += ["", f"## {GROUP_LABEL[g]}: CD per class (seen t*), mean ± 95 % interval", ""]
        lines.append("| method | " + " | ".join(classes) + " | mean |")
        lines.append("|---|" + "---|" * (len(classes) + 1))
        idx = {(c["row"], c["class"]): c for c in per_class}
        for row in rows:
            cells = [_fmt(idx[(row, c)]["cd1k_seen"], idx[(row, c)]["cd1k_seen_ci95"]) if (row, c) in idx else "–" for c in classes]
            lines.append(f"| {row} | " + " | ".join(cells) + f" | {_fmt(groups['seen'][g].get(row, math.nan))} |")
        counts = [f"{c}: {idx[(rows[0], c)]['shapes']} shapes / {idx[(rows[0], c)]['views']} views" for c in classes if (rows[0], c) in idx]
        lines += ["", "Counts: " + "; ".join(counts) + "."]
        lines += ["", f"### {GROUP_LABEL[g]}: details", "",
                  "| method | class | shapes | views | CD (seen t*) | CD (best t/class) | t/class | CD10k | F@1% | F@2% | empty meshes |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for row in rows:
            for c in classes:
                e = idx.get((row, c))
                if e is None:
                    continue
                tc = "–" if row in (FLOOR, "Nearest training shape") else f"{e['threshold_per_class']:.2f}"
                lines.append(f"| {row} | {c} | {e['shapes']} | {e['views']} | {_fmt(e['cd1k_seen'], e['cd1k_seen_ci95'])} | {_fmt(e['cd1k_per_class'])} | {tc} | "
                             f"{_fmt(e['cd10k_seen'])} | {_fmt(e['f1_seen'])} | {_fmt(e['f2_seen'])} | {e['empty_seen']} |")
    return "\n".join(lines) + "\n"


def depth_width_ratios(records: list[dict], row: str, level: float, group: str = "flat-from-above"):
    """(prediction, truth, ratio) arrays of the depth ÷ width of ``row``'s views of ``group`` at ``level``, from
    ``per_view.csv`` records (``dw@t`` and ``dw_true``, :func:`genre_backend.geometry.metrics.depth_over_width`);
    a ratio is the prediction's over the truth's (nan where either is undefined)."""
    import numpy as np

    t = threshold_key(level)
    recs = [r for r in records if r["row"] == row and group in r["groups"].split("|")]
    pred = np.array([float(r[f"dw@{t}"]) for r in recs])
    true = np.array([float(r["dw_true"]) for r in recs])
    with np.errstate(divide="ignore", invalid="ignore"):
        return pred, true, pred / true


def flatness_table(records: list[dict], choice: dict, rows: list[str], group: str = "flat-from-above") -> str:
    """Depth ÷ width of the views of ``group`` (Markdown, empty when none): per row, at its seen t*.

    The ratio of a view is the prediction's depth ÷ width over the truth's
    (``dw@t`` over ``dw_true``, :func:`genre_backend.geometry.metrics.depth_over_width`);
    the medians are over views, "within 2×" counts views whose ratio lies in [0.5, 2].
    """
    import numpy as np

    views = [r for r in records if group in r["groups"].split("|")]
    if not views:
        return ""
    lines = ["", f"## {GROUP_LABEL.get(group, group)}: depth ÷ width (seen t*)", "",
             "Depth: the height along the object's up; width: the largest spread across it (trimmed 0.2 %). "
             "Ratio: the prediction's over the truth's, per view; 1 is right.", "",
             "| method | views | depth ÷ width (median) | truth (median) | ratio (median) | within 2× | CD (mean) |",
             "|---|---|---|---|---|---|---|"]
    for row in list(rows) + [FLOOR]:
        recs = [r for r in views if r["row"] == row]
        if not recs or row not in choice["seen"]:
            continue
        t = threshold_key(choice["seen"][row])
        pred, true, ratio = depth_width_ratios(recs, row, choice["seen"][row], group)
        ok = np.isfinite(ratio)
        within = int(((ratio >= 0.5) & (ratio <= 2.0) & ok).sum())
        cd = float(np.mean([float(r[f"cd1k@{t}"]) for r in recs]))
        med = lambda a: float(np.median(a[np.isfinite(a)])) if np.isfinite(a).any() else math.nan  # noqa: E731
        lines.append(f"| {row} | {len(recs)} | {_fmt(med(pred))} | {_fmt(med(true))} | {_fmt(med(ratio))} | "
                     f"{within} / {len(recs)} | {_fmt(cd)} |")
    return "\n".join(lines) + "\n"


def sweep_table(records: list[dict], sweeps, level: float) -> str:
    """``genre eval --sweep``'s table (Markdown, empty without sweeps): for each swept mesh option, per view group,
    the mean CD and the share of closed meshes of GenRe at the weights' own level at each value, beside the
    weights' own setting (row ``GenRe``).  Where ``hole_closing`` is swept and seen-test views are present, the
    rule that picks it (:func:`training.eval.statistics.choose_hole_closing`, seen-test closed shares) is applied."""
    from .rows import sweep_row
    from .statistics import choose_hole_closing

    if not sweeps:
        return ""
    t = threshold_key(level)
    groups = sorted({g for r in records for g in r["groups"].split("|")})
    lines = ["", f"## Mesh option sweeps (level {level:.2f}, the weights' own)", "",
             "Each row is GenRe with one option changed, the networks run once; CD the mean over the group's views, "
             "closed the share of meshes without holes or tunnels.", "",
             "| option | value | " + " | ".join(f"{GROUP_LABEL.get(g, g)} CD | closed" for g in groups) + " |",
             "|---|---|" + "---|---|" * len(groups)]

    def cells(row: str) -> tuple[list[str], dict[str, float]]:
        out, closed = [], {}
        for g in groups:
            recs = [r for r in records if r["row"] == row and g in r["groups"].split("|")]
            cd = [float(r[f"cd1k@{t}"]) for r in recs]
            cl = [float(r[f"closed@{t}"]) for r in recs]
            closed[g] = sum(cl) / len(cl) if cl else math.nan
            out += [_fmt(sum(cd) / len(cd) if cd else math.nan), _fmt(closed[g])]
        return out, closed

    notes = []
    for name in dict.fromkeys(n for n, _ in sweeps):
        own, _ = cells("GenRe")
        lines.append(f"| {name} | the weights' | " + " | ".join(own) + " |")
        shares = {}
        for n, v in sweeps:
            if n == name:
                row_cells, closed = cells(sweep_row(n, v))
                shares[v] = closed.get("test", math.nan)
                lines.append(f"| {name} | {v} | " + " | ".join(row_cells) + " |")
        if name == "hole_closing" and "test" in groups:
            try:
                notes.append(f"hole_closing by its rule (the least sealing whose seen-test closed share reaches 90 %): "
                             f"**{choose_hole_closing(shares)}**")
            except ValueError:
                pass
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


def pyplot():
    """matplotlib's pyplot on the Agg backend (no screen)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> None:
    """Save a figure as PNG atomically and close it."""
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110, bbox_inches="tight"))
    pyplot().close(fig)
