#!/usr/bin/env python3
"""Print the table of docs/diagnose.md ("Acceptance results") from the acceptance cases.

Runs every case of ``tests/diagnosis/test_diagnose_acceptance.py`` (the simulated drive with a
hidden effect the model lacks, diagnosed and refitted with the suggestion) and prints one
Markdown row per case: the rank of the hidden effect(s), the share of the residual
variance the first candidate explains, the residual RMS before and after adding, the
floor (the true model with the true parameters), the largest parameter error against
the truth and the largest fixed-point against float difference.

    .venv/bin/python tools/acceptance_table.py > /tmp/table.md
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _cases() -> object:
    spec = importlib.util.spec_from_file_location(
        "acceptance", ROOT / "tests" / "diagnosis" / "test_diagnose_acceptance.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["acceptance"] = mod
    spec.loader.exec_module(mod)
    return mod


def main() -> int:
    acc = _cases()
    print("| case | rank of the hidden effect(s) | explained (1st) | RMS before | RMS after "
          "| floor (true model) | after / floor | largest parameter error "
          "| largest fixed−float |")
    print("|---|---|---|---|---|---|---|---|---|")
    for case in acc.CASES:  # type: ignore[attr-defined]
        out = acc._run(case)  # type: ignore[attr-defined]
        rep = out.report
        names = [c.effect for c in rep.candidates]
        ranks = ", ".join(str(names.index(h) + 1) if h in names else "-" for h in case.hidden)
        unit = out.after.primary.fit.unit
        before, after = rep.before.residual_rms, out.after.residual_rms
        floor = acc._floor(out)  # type: ignore[attr-defined]
        truth = out.res.params
        errs = {p.name: p.value / truth[p.name] - 1.0 for p in out.after.estimates.parameters}
        worst = max(errs, key=lambda k: abs(errs[k]))
        fx = {p.name: abs(p.fixed - p.value) / abs(p.value)
              for p in out.after.estimates.parameters}
        fworst = max(fx, key=lambda k: fx[k])
        label = case.id.replace("+", " + ")
        print(f"| {label} | {ranks} | {100 * rep.candidates[0].explained:.1f} % "
              f"| {before:.3g} {unit} | {after:.3g} {unit} | {floor:.3g} {unit} "
              f"| {after / floor:.3f} | {100 * errs[worst]:+.2f} % ({worst}) "
              f"| {100 * fx[fworst]:.3f} % ({fworst}) |")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
