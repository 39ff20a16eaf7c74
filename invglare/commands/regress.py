"""``invglare regress``: the golden regression suite, and fits of the eye model to the CIE GSF."""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from invglare.errors import ConfigError
from invglare.files.outputs import output_file, output_folder

log = logging.getLogger("invglare")


def run_regress(
    cases: list[str],
    update: bool,
    reason: str | None,
    golden_dir: Path,
    out_dir: Path,
    list_only: bool = False,
) -> None:
    """Run the golden suite (or update it); exit 1 naming the failing cases.

    Raises `ConfigError` for `--reason` without `--update` (or the reverse) and for
    unknown case names.
    """
    from invglare.regress import (
        CASES,
        run_suite,
        select_cases,
        update_goldens,
        write_report,
    )

    if list_only:
        for case in select_cases(cases):
            typer.echo(f"{case.name}: {case.description}")
        return
    if reason is not None and not update:
        raise ConfigError("--reason is recorded only with --update; add --update or drop it")
    if update and not (reason or "").strip():
        raise ConfigError(
            "--update needs --reason TEXT saying why the stored PSFs change "
            f"(it is recorded in {golden_dir / 'CHANGES.md'})"
        )
    if not update and not golden_dir.is_dir():
        raise ConfigError(
            f"golden folder {golden_dir} does not exist; run from the repository root or pass "
            "--golden-dir (create the goldens with --update --reason TEXT)"
        )
    select_cases(cases)  # unknown names fail before any model is built
    output_folder(out_dir, "--out-dir")
    output_file(Path(out_dir) / "regression.md", "--out-dir", (".md",))
    if update:
        output_folder(golden_dir, "--golden-dir")
    results = run_suite(cases, golden_dir)
    updated: list[str] = []
    if update:
        updated = update_goldens(results, golden_dir, reason or "")
    report = write_report(results, out_dir, updated=updated, golden_dir=golden_dir)
    for r in results:
        if r.metrics is None:
            detail = r.failures[0]
        else:
            m = r.metrics
            detail = (
                f"rel L2 {m.rel_l2:.2e}, max err {m.max_err:.2e}, SSIM(log) {m.ssim_log:.6f}, "
                f"PSNR {m.psnr_db:.1f} dB, EE {m.ee_diff:.2e}"
            )
        log.info("%-26s %-7s %s", r.case.name, r.status, detail)
    log.info("wrote %s and %d figures in %s", report, len(results), report.with_suffix(""))
    if update:
        log.info(
            "updated %d golden(s) in %s: %s",
            len(updated),
            golden_dir,
            ", ".join(updated) or "none (all bit-identical)",
        )
        return
    failed = [r for r in results if not r.passed]
    if failed:
        for r in failed:
            typer.echo(f"FAIL {r.case.name}: {'; '.join(r.failures)}", err=True)
        names = ", ".join(r.case.name for r in failed)
        typer.echo(
            f"invglare regress: {len(failed)} of {len(results)} case(s) failed: {names} "
            f"(see {report})",
            err=True,
        )
        raise typer.Exit(code=1)
    n_all = len(CASES)
    scope = "all" if len(results) == n_all else f"{len(results)} of {n_all}"
    log.info("regression passed: %s cases within tolerance", scope)


def run_cie(specs: list[str], out_dir: Path) -> None:
    """Fit the eye model to the CIE GSF for each ``AGE,PIGMENT``; write OUT_DIR/cie/."""
    from invglare.cie_study import CieFitSetup, fit_cie, parse_cie_spec, write_cie_report
    from invglare.commands.options import named

    # Every spec is checked before the first (minutes-long) fit starts.
    with named("--cie"):
        pairs = [parse_cie_spec(s) for s in specs]
    output_folder(out_dir, "--out-dir")
    setup = CieFitSetup()
    log.info(
        "fitting %d CIE GSF(s) over %.3g-%.3g deg (the model's alias-free range at %d pupil "
        "samples); the first fit compiles the model",
        len(pairs),
        setup.theta_min_deg,
        setup.max_angle_deg(),
        setup.aperture_npix,
    )
    results = []
    for age, pigmentation in pairs:
        result = fit_cie(age, pigmentation, setup, progress=None)
        log.info("%s", result.summary())
        results.append(result)
    path = write_cie_report(results, out_dir)
    log.info("wrote %s", path)
