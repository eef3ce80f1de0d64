"""The figures of an identification: fit.png (each measured column against the identified
model, the fit's samples and the validation's) and residuals.png (their residuals)."""

from __future__ import annotations

from pathlib import Path

from dscjax.identify.fit import fitted
from dscjax.plotting import AXIS_LABEL, saved


def write(out: Path, res) -> None:
    # {column: [(tag, t, y measured, y model) on the fitted samples]} of the fit and validation
    curves = {c: [] for c in res.problem.record.y}
    for tag, problem, fit in (("fit", res.problem, res.fit),
                              ("validation", res.val_problem, res.val_fit)):
        for c, curve in fitted(problem, fit).items():
            curves[c].append((tag, *curve))
    columns = list(curves)
    for name, residual in (("fit.png", False), ("residuals.png", True)):
        with saved(out / name, None, len(columns), 1, figsize=(8, 2.4 * len(columns)),
                   squeeze=False) as (fig, axes):
            for ax, c in zip(axes[:, 0], columns, strict=True):
                for tag, t, y, yh in curves[c]:
                    colour = "#1f77b4" if tag == "fit" else "#d62728"
                    if residual:
                        ax.plot(t, y - yh, color=colour, lw=0.8, label=f"{tag}: measured - model")
                    else:
                        ax.plot(t, y, color="#999999", lw=0.8, label=f"{tag}: measured")
                        ax.plot(t, yh, color=colour, lw=1.2, label=f"{tag}: model")
                ax.set_ylabel(c)
                ax.legend(fontsize=7, loc="upper right")
            axes[-1, 0].set_xlabel(AXIS_LABEL["t"])
            fig.suptitle("residuals" if residual else "measured and identified model")
