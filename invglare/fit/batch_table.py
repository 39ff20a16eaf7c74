"""The table of a batch fit: every photo's parameters ± standard errors, status and time.

Built from the photos' report folders (their ``params.json``) and the outcomes of the run
(:class:`~invglare.fit.batch.Outcome`), so a resumed batch tabulates the photos fitted
before it too. Written atomically as

- ``batch.csv``: one row per photo: ``photo``, ``name``, ``status`` (``ok``, ``not
  converged``, ``poor fit`` (converged, but the residuals are far above the noise),
  ``failed``), ``converged``, ``reduced_chi2``, ``loss``, ``n_steps``, ``wall_s`` (load,
  fit and report), ``compile_s``, ``solve_s``; per parameter its value, ``PATH se`` and,
  where the truth is known, ``PATH truth``; and ``reason``;
- ``batch.md``: the same as a markdown table (value ± standard error), a recovery summary
  per parameter with a known truth (largest error, largest relative error, how many
  photos' truth lies within two standard errors), the failures with their reasons, and
  the population figures (:mod:`invglare.fit.batch_figures`).

**Example:**

```python
rows = collect_rows(tasks, outcomes, photos)
write_table(Path("reports/eye_population/batch"), rows, title="eye_population")
```
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from invglare.files.atomic import write_text_atomic
from invglare.fit.batch import Outcome, Task, finished
from invglare.fit.report import unit_of
from invglare.fit.result import FitResult
from invglare.fit.trust import poor_fit

#: Relative errors are reported for truths at least this far from 0 (else absolute only).
_REL_MIN = 1e-12


@dataclasses.dataclass(frozen=True)
class PhotoRow:
    """One photo in the table: its outcome and, when a report was written, its result."""

    name: str
    photo: str
    status: str
    reason: str
    result: FitResult | None
    wall_s: float | None = None

    @property
    def failed(self) -> bool:
        return self.status != "ok"


def collect_rows(
    tasks: Sequence[Task], outcomes: Sequence[Outcome], photos: Mapping[str, str]
) -> list[PhotoRow]:
    """One :class:`PhotoRow` per task, in the tasks' order.

    A photo with a fit result in its folder (fitted now or before) is ``ok`` or ``not
    converged`` by that result; one without is ``failed`` with its outcome's reason.
    `photos`: ``{name: the photo's path as shown}``.
    """
    by_name = {o.name: o for o in outcomes}
    rows = []
    for task in tasks:
        outcome = by_name.get(task.name)
        result = finished(task.folder)
        if result is None:
            reason = outcome.reason if outcome else "not fitted (the run was interrupted)"
            rows.append(PhotoRow(task.name, photos.get(task.name, ""), "failed", reason, None))
            continue
        status, reason = status_of(result)
        rows.append(
            PhotoRow(task.name, photos.get(task.name, ""), status, reason, result,
                     _wall_s(task.folder))
        )  # fmt: skip
    return rows


def status_of(result: FitResult) -> tuple[str, str]:
    """``("ok", "")``, or ``("not converged" | "poor fit", the fit's message)``: a poor fit
    converged, but its noise-normalised residuals are far above the noise (a `reduced_chi2`
    flag above 1, :func:`invglare.fit.trust.poor_fit`)."""
    if not result.converged:
        return "not converged", result.message
    if poor_fit(result.flags, result.message):
        return "poor fit", result.message
    return "ok", ""


def _wall_s(folder: Path) -> float | None:
    try:
        data = json.loads((Path(folder) / "params.json").read_text(encoding="utf-8"))
        value = data.get("fit", {}).get("wall_s")
        return None if value is None else float(value)
    except (OSError, ValueError, AttributeError, TypeError):
        return None


def parameter_paths(rows: Sequence[PhotoRow]) -> list[str]:
    """Every fitted path, in the order the photos list them."""
    paths: dict[str, None] = {}
    for row in rows:
        if row.result is not None:
            paths.update(dict.fromkeys(row.result.paths))
    return list(paths)


def short_names(paths: Sequence[str]) -> dict[str, str]:
    """The shortest dotted tail of each path that no other path ends with."""
    out = {}
    for path in paths:
        parts = path.split(".")
        for k in range(1, len(parts) + 1):
            tail = ".".join(parts[-k:])
            if not any(o != path and (o == tail or o.endswith("." + tail)) for o in paths):
                break
        out[path] = tail
    return out


def _num(x: float | None) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return ""
    return repr(float(x))


def to_csv(rows: Sequence[PhotoRow]) -> str:
    """``batch.csv`` (module docstring)."""
    paths = parameter_paths(rows)
    truths = [p for p in paths if any(r.result and r.result.truth and p in r.result.truth
                                      for r in rows)]  # fmt: skip
    header = ["photo", "name", "status", "converged", "reduced_chi2", "loss", "n_steps",
              "wall_s", "compile_s", "solve_s"]  # fmt: skip
    for p in paths:
        header += [p, f"{p} se"] + ([f"{p} truth"] if p in truths else [])
    header.append("reason")
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        res = row.result
        cells = [row.photo, row.name, row.status]
        if res is None:
            cells += [""] * 7
        else:
            cells += [
                str(bool(res.converged)).lower(),
                _num(res.reduced_chi2),
                _num(res.loss),
                str(res.n_steps),
                _num(row.wall_s),
                _num(res.timing_s.get("compile")),
                _num(res.timing_s.get("solve")),
            ]
        for p in paths:
            has = res is not None and p in res.values
            cells += [_num(res.values[p]) if has else "", _num(res.stderr[p]) if has else ""]
            if p in truths:
                truth = res.truth.get(p) if res is not None and res.truth else None
                cells.append(_num(truth))
        cells.append(row.reason)
        writer.writerow(cells)
    return buffer.getvalue()


def _pm(value: float, stderr: float) -> str:
    if not math.isfinite(stderr):
        return f"{value:.5g} ± —"
    return f"{value:.5g} ± {stderr:.2g}"


def recovery(rows: Sequence[PhotoRow]) -> list[dict[str, float | int | str]]:
    """Per parameter with a known truth: photos, largest error, largest relative error,
    root-mean-square error, and how many truths lie within 2 standard errors."""
    out = []
    for p in parameter_paths(rows):
        pairs = [
            (r.result.values[p], r.result.stderr[p], r.result.truth[p])
            for r in rows
            if r.result is not None and r.result.truth and p in r.result.truth
        ]
        if not pairs:
            continue
        errors = [v - t for v, _, t in pairs]
        rel = [abs(v - t) / abs(t) for v, _, t in pairs if abs(t) > _REL_MIN]
        within = sum(1 for v, s, t in pairs if math.isfinite(s) and abs(v - t) <= 2 * s)
        out.append(
            {
                "path": p,
                "n": len(pairs),
                "max_abs_error": max(abs(e) for e in errors),
                "max_rel_error": max(rel) if len(rel) == len(pairs) else math.nan,
                "rms_error": math.sqrt(sum(e * e for e in errors) / len(errors)),
                "within_2se": within,
            }
        )
    return out


def to_markdown(
    rows: Sequence[PhotoRow], *, title: str, figures: Sequence[str] = (), notes: Sequence[str] = ()
) -> str:
    """``batch.md`` (module docstring); `figures` are file names beside it, `notes` lines
    said under the title (the command, the cluster, the wall time)."""
    paths = parameter_paths(rows)
    names = short_names(paths)
    counts = {s: sum(r.status == s for r in rows) for s in ("ok", "poor fit", "not converged")}
    n_failed = len(rows) - sum(counts.values())
    lines = [
        f"# Batch fit: {title}",
        "",
        f"{len(rows)} photos: {counts['ok']} converged, {counts['poor fit']} converged to a poor "
        f"fit, {counts['not converged']} not converged, {n_failed} failed.",
        "",
        *[f"- {note}" for note in notes],
    ]
    if notes:
        lines.append("")
    units = {p: unit_of(p) for p in paths}
    head = ["photo", "status", *[f"{names[p]}" + (f" ({units[p]})" if units[p] else "")
                                 for p in paths], "reduced χ²", "steps", "time s"]  # fmt: skip
    lines += [
        "Each parameter: fitted value ± standard error; time: load, fit and report of the "
        "photo on its worker (compilation included where the worker compiled).",
        "",
        "| " + " | ".join(head) + " |",
        "|---|---|" + "---:|" * (len(head) - 2),
    ]
    for row in rows:
        res = row.result
        link = f"[{row.name}]({row.name}/report.md)" if res is not None else row.name
        cells = [link, row.status]
        for p in paths:
            has = res is not None and p in res.values
            cells.append(_pm(res.values[p], res.stderr[p]) if has else "")
        if res is None:
            cells += ["", "", ""]
        else:
            chi2 = res.reduced_chi2
            cells += [
                f"{chi2:.4g}" if math.isfinite(chi2) else "—",
                str(res.n_steps),
                f"{row.wall_s:.1f}" if row.wall_s is not None else "",
            ]
        lines.append("| " + " | ".join(cells) + " |")
    rec = recovery(rows)
    if rec:
        lines += [
            "",
            "## Recovery of the known truth",
            "",
            "| parameter | photos | largest error | largest relative error | rms error "
            "| truth within 2 SE |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for r in rec:
            rel = r["max_rel_error"]
            rel_text = f"{100 * rel:.3g} %" if math.isfinite(rel) else "—"
            lines.append(
                f"| {r['path']} | {r['n']} | {r['max_abs_error']:.3g} | {rel_text} "
                f"| {r['rms_error']:.3g} | {r['within_2se']}/{r['n']} |"
            )
    failures = [r for r in rows if r.failed]
    if failures:
        lines += ["", "## Failures", ""]
        lines += [f"- **{r.name}** ({r.status}): {r.reason}" for r in failures]
    if figures:
        lines += ["", "## Population", ""]
        lines += [f"![{Path(f).stem}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def write_table(
    folder: Path,
    rows: Sequence[PhotoRow],
    *,
    title: str,
    figures: Sequence[str] = (),
    notes: Sequence[str] = (),
) -> tuple[Path, Path]:
    """Write ``batch.csv`` and ``batch.md`` into `folder`, atomically. **Returns:** both."""
    folder = Path(folder)
    csv_path = write_text_atomic(folder / "batch.csv", to_csv(rows))
    md = to_markdown(rows, title=title, figures=figures, notes=notes)
    return csv_path, write_text_atomic(folder / "batch.md", md)
