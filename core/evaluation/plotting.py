"""Showing evaluation results: the summary table, JSON, and the paper's Figure 4 boxplots
(matplotlib's Agg canvas: no pyplot, no Qt; the GUI embeds the same Figure). The counterpart of
scikit-learn's ``Display`` objects: it draws results, it computes nothing.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

LABELS = {
    "reconstruction": ("e", "reconstruction error"),
    "generalisation": ("g", "generalisation error"),
    "specificity": ("s", "specificity error"),
    "sparse_reconstruction": ("g0.05", "sparse reconstruction error"),
}
PER_SHAPE_MEASURES = tuple(LABELS)


def summary_rows(results: dict[str, dict]) -> list[dict[str, Any]]:
    """One row per method: mean over shapes of each measure's avg and max (mm), compactness."""
    rows = []
    for method, res in results.items():
        row: dict[str, Any] = {"method": method, "n_factors": res.get("n_factors")}
        for name in PER_SHAPE_MEASURES:
            if name in res:
                short = LABELS[name][0]
                row[f"{short}_avg"] = float(np.mean(res[name]["avg"]))
                row[f"{short}_max"] = float(np.mean(res[name]["max"]))
        if "compactness" in res and len(res["compactness"]):
            row["explained"] = float(res["compactness"][-1])
        rows.append(row)
    return rows


def summary_table(results: dict[str, dict]) -> str:
    """A plain-text table of :func:`summary_rows` (means over shapes, mm)."""
    rows = summary_rows(results)
    cols = ["method", "n_factors"] + [c for c in ("e_avg", "e_max", "g_avg", "g_max", "s_avg",
                                                  "s_max", "g0.05_avg", "g0.05_max", "explained")
                                      if any(c in r for r in rows)]
    lines = [" ".join(f"{c:>10}" for c in cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            cells.append(f"{v:>10.3f}" if isinstance(v, float) else f"{v!s:>10}")
        lines.append(" ".join(cells))
    return "\n".join(lines)


def to_json(results: dict[str, dict]) -> dict[str, Any]:
    """Results with numpy arrays as lists (for ``core.io.atomic_write_json``)."""
    def conv(v):
        if isinstance(v, np.ndarray):
            return v.tolist()
        if isinstance(v, np.generic):
            return v.item()
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return v
    return {"units": "mm", "methods": conv(results), "summary": summary_rows(results)}


def plot_metrics(results: dict[str, dict], path: str | os.PathLike | None = None,
                 title: str | None = None):
    """Boxplots like Figure 4 of the paper: one panel per measure (avg top row, max bottom),
    plus the compactness curves. Uses the Agg canvas (no pyplot, no Qt); saves to ``path``
    (atomically) if given. Returns the matplotlib Figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    methods = list(results)
    present = [m for m in PER_SHAPE_MEASURES if any(m in r for r in results.values())]
    has_comp = any("compactness" in r for r in results.values())
    ncols = len(present) + (1 if has_comp else 0)
    fig = Figure(figsize=(3.2 * max(ncols, 1), 6.0), constrained_layout=True)
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, max(ncols, 1), squeeze=False)
    for col, name in enumerate(present):
        short, long = LABELS[name]
        for row, stat in enumerate(("avg", "max")):
            ax = axes[row, col]
            data = [np.asarray(results[m][name][stat]) if name in results[m] else np.array([])
                    for m in methods]
            key = "tick_labels" if _has_tick_labels() else "labels"
            ax.boxplot(data, **{key: methods})
            ax.set_ylabel(f"{short} {stat} [mm]")
            if row == 0:
                ax.set_title(long)
            ax.tick_params(axis="x", labelrotation=45)
            ax.grid(axis="y", alpha=0.3)
    if has_comp:
        ax = axes[0, ncols - 1]
        for m in methods:
            if "compactness" in results[m]:
                c = np.asarray(results[m]["compactness"])
                ax.plot(np.arange(1, len(c) + 1), c, label=m)
        ax.set_xlabel("number of factors")
        ax.set_ylabel("cumulative variance explained")
        ax.set_title("compactness")
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize="small")
        ax.grid(alpha=0.3)
        axes[1, ncols - 1].axis("off")
    if title:
        fig.suptitle(title)
    if path is not None:
        from core.io import atomic_path

        with atomic_path(path) as tmp:
            fig.savefig(str(tmp), dpi=110, format=os.path.splitext(str(path))[1][1:] or "png")
    return fig


def _has_tick_labels() -> bool:
    import matplotlib

    major, minor = (int(x) for x in matplotlib.__version__.split(".")[:2])
    return (major, minor) >= (3, 9)


__all__ = ["LABELS", "PER_SHAPE_MEASURES", "summary_rows", "summary_table", "to_json", "plot_metrics"]
