"""``recal static``: lab calibration from a CSV table of still positions, one row each.

The table's x, y, z columns (any unit) are read by header; the fit is `recal.core.static`'s
(Bragge's linear fit with known orientations, else a full sensitivity matrix and offsets
fitted so that every row's norm is 1 g); the report gives each row's relative norm error.
"""

from __future__ import annotations

import csv
from typing import Any

import numpy as np

from recal.core import static
from recal.errors import InputError, UsageError

__all__ = ["parse_rows", "read_static_table", "static_report"]


def parse_rows(spec: str | None, n: int) -> np.ndarray:
    """``--fit-rows``: a mask of the rows named, 1-based (``1-20`` or ``1-6,9``; all if
    empty)."""
    mask = np.zeros(n, bool)
    if not spec:
        mask[:] = True
        return mask
    for part in spec.split(","):
        lo, _, hi = part.partition("-")
        try:
            i, j = int(lo), int(hi or lo)
        except ValueError:
            raise UsageError(f"--fit-rows: {part!r} is not a row number or range") from None
        if not 1 <= i <= j <= n:
            raise UsageError(f"--fit-rows: {part!r} is outside rows 1-{n}")
        mask[i - 1:j] = True
    return mask


def read_static_table(path: str) -> np.ndarray:
    """The three readings of each row: columns x,y,z (any unit, any suffix) by header."""
    try:
        with open(path, newline="") as f:
            rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
    except OSError as e:
        raise InputError(f"cannot read {path}: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not UTF-8 text (byte {e.start})") from None
    if len(rows) < 2:
        raise InputError(f"{path}: needs a header and at least one row")
    head = [h.strip().lower() for h in rows[0]]
    cols = []
    for axis in "xyz":
        hit = [i for i, h in enumerate(head) if h == axis or h.startswith(axis + "_")]
        if not hit:
            raise InputError(f"{path}: no column {axis!r} (or {axis}_<unit>) in header {head}")
        cols.append(hit[0])
    try:
        return np.array([[float(r[c]) for c in cols] for r in rows[1:]])
    except (ValueError, IndexError) as e:
        raise InputError(f"{path}: a row is not three numbers ({e})") from None


def static_report(v: np.ndarray, fit_rows: np.ndarray, *, known_orientations: bool,
                  g: float | None, full: bool, loss: str) -> tuple[dict[str, Any], list[str]]:
    """Fit the rows ``fit_rows`` of ``v``: the report (parameters, each row's relative norm
    error, the worst over all, fitted and held-out rows) and its lines for a person."""
    if known_orientations:
        fit = static.fit_known_orientations(v, fit_rows, g)
    else:
        fit = static.fit_unknown_orientations(v, fit_rows, g, full=full, loss=loss)
    err = fit.rel_norm_error
    rows = [{"row": i + 1, "fitted": bool(fit.fit_rows[i]), "rel_norm_error": float(e)}
            for i, e in enumerate(err)]
    warning = _undetermined(fit)
    report = {"method": fit.method, "g": fit.g, "params": fit.params, "rows": rows,
              "usable": warning is None, "warning": warning,
              "worst_rel_norm_error": float(err.max()),
              "worst_rel_norm_error_fitted": float(err[fit.fit_rows].max()),
              "worst_rel_norm_error_held_out": (float(err[~fit.fit_rows].max())
                                                if (~fit.fit_rows).any() else None)}
    lines = [f"{'row':>4} {'fit':>4} {'|a|/g-1 (%)':>12}"]
    for r in rows:
        lines.append(f"{r['row']:>4} {'*' if r['fitted'] else '':>4} "
                     f"{100 * r['rel_norm_error']:>12.3f}")
    lines.append(f"worst relative norm error: {100 * err.max():.3f} % over all rows "
                 f"({100 * err[fit.fit_rows].max():.3f} % on the {fit.fit_rows.sum()} fitted "
                 "rows)")
    if "axis_angles_deg" in fit.params:
        ang = fit.params["axis_angles_deg"]
        lines.append("angles between sensing axes: "
                     + ", ".join(f"{k} {v:.3f}" for k, v in ang.items()))
    if warning is not None:
        lines.append(f"warning: {warning}")
    return report, lines


def _undetermined(fit: static.StaticFit) -> str | None:
    """Why the fit's parameters mean nothing (None: they are determined). A small norm error
    on such rows only says they were fitted, not that the axes are known."""
    d = fit.params.get("determination")
    if d is None or d >= static.MIN_DETERMINATION:
        return None
    what = ("the axes' angles, offsets and gains" if "axis_angles_deg" in fit.params
            else "the offsets and gains")
    return (f"the fitted rows do not cover enough orientations to determine {what} "
            f"(determination {d:.1e} < {static.MIN_DETERMINATION:g}): the result is not "
            f"usable; record still poses spread over the sphere (six faces and tilts "
            f"between them; the full model's angles need tilted poses, not faces alone)")
