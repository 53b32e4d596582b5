#!/usr/bin/env python3
"""The scorecard of cli/measured_cases.sh: one row per case from <OUT>/data/<case>/truth.json and the runs'
<OUT>/<case>/{recording,clean}/diagnose/diagnosis.json (`mpsim diagnose`'s summary: src/mpsim/commands/diagnose.py).

Pass rule ("holds"): on the recording, the truth's kind on the truth's row with the coefficient within 10 % and
nothing else named — or, for a missing effect outside mpsim's library (kind null), verdict "unexplained
structured residual" with nothing named; on the clean twin, nothing named; and no returned model (fix=true) worse
on held-out data than the model given. Writes <OUT>/scorecard.md and prints it.

Case a, the real recordings (cli/dfki_pendulum.sh, its OUT given as the second argument, default
<OUT>/a_dfki), has no truth: its row reports the verdict, what was named and the held-out errors, and "holds"
only says whether the returned model is no worse than the one given.

Usage: ``python cli/measured_scorecard.py <OUT> [<DFKI_OUT>]``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

BOUND = 0.10  # relative error allowed on the coefficient
UNEXPLAINED = "unexplained structured residual"


def _load(run: Path) -> tuple[dict[str, Any] | None, str]:
    """(diagnosis.json's content, "") or (None, why there is none)."""
    d = run / "diagnose" / "diagnosis.json"
    if d.exists():
        return json.loads(d.read_text()), ""
    if not run.exists():
        return None, "not run"
    log = run.with_suffix(".log")
    tail = log.read_text().strip().splitlines()[-1:] if log.exists() else []
    stage = "train" if not (run / "train" / "checkpoints" / "best.ckpt").exists() else "diagnose"
    return None, f"{stage} failed: {tail[0][:100] if tail else '(nothing in its log)'}"


def _named(r: dict[str, Any]) -> str:
    return "; ".join(
        f"{t['label']} ({', '.join(f'{k} {v:.4g}' for k, v in t['values'].items())})" for t in r["effects_named"]
    )


def _tested(r: dict[str, Any]) -> str:
    """The candidates judged on held-out data, with the share of the error they left ("dv/dt: X(v)" shortened)."""
    trials = r["judgement"]["trials"]
    return ", ".join(t["label"].split(": ", 1)[-1] for t in trials) or "none"


def _errors(r: dict[str, Any]) -> tuple[str, bool]:
    """("before → after" held-out rollout RMSE, whether the returned model is worse)."""
    b, a = r["before"]["rollout_rmse"], (r["after"] or {}).get("rollout_rmse")
    if a is None:
        return f"{b:.3g} (unchanged)", False
    return f"{b:.3g} → {a:.3g}", a > b


def _wall(run: Path) -> str:
    f = run / "wall_s"
    return f.read_text().strip() if f.exists() else "?"


def score(out: Path, case: str) -> tuple[list[str], bool]:
    """The row of `case` and whether it holds."""
    truth = json.loads((out / "data" / case / "truth.json").read_text())
    miss = truth["missing_effect"]
    kind, row = miss["kind"], miss["target"]
    truth_text = (
        f"{kind}({miss['source']}) on d{row}/dt, coef {miss['coef']:.4g}"
        if kind
        else f"{next(iter(miss['physical']))} {next(iter(miss['physical'].values()))} (no such kind: unexplained)"
    )
    rec, why = _load(out / case / "recording")
    clean, why_clean = _load(out / case / "clean")
    ok = True
    if rec is None or "error" in rec:
        verdict, named, coef_err, errors, tested = why or f"ERROR: {rec['error'][:80]}", "", "", "", ""  # type: ignore[index]
        ok = False
    else:
        verdict, named, (errors, worse) = rec["verdict"], _named(rec) or "—", _errors(rec)
        tested = _tested(rec)
        ok = not worse
        coef_err = ""
        if kind:
            hits = [t for t in rec["effects_named"] if t["kind"] == kind and t["label"].startswith(f"d{row}/dt")]
            if hits:
                rel = abs(hits[0]["values"]["coef"] - miss["coef"]) / abs(miss["coef"])
                coef_err = f"{hits[0]['values']['coef']:.4g} vs {miss['coef']:.4g} ({rel:.1%})"
                ok = ok and rel <= BOUND and len(rec["effects_named"]) == 1
            else:
                ok = False
        else:
            ok = ok and verdict == UNEXPLAINED and not rec["effects_named"]
    if clean is None or "error" in clean:
        clean_text = why_clean or f"ERROR: {clean['error'][:80]}"  # type: ignore[index]
        ok = False
    else:
        clean_errors, clean_worse = _errors(clean)
        clean_text = f"{clean['verdict']}; {_named(clean) or 'nothing named'}; {clean_errors}"
        ok = ok and not clean["effects_named"] and not clean_worse
    wall = f"{_wall(out / case / 'recording')} + {_wall(out / case / 'clean')}"
    row = [case, truth_text, verdict, named, coef_err, tested, errors, clean_text, wall, "yes" if ok else "NO"]
    return row, ok


def real_row(run: Path) -> tuple[list[str], bool] | None:
    """Case a's row (no truth: the verdict and errors as measured), None when the recipe has not run there."""
    rec, why = _load(run)
    if rec is None and why == "not run":
        return None
    truth = "real pendulum (lab: Fv 0.047 N m s, Fc 0.184 N m)"
    if rec is None or "error" in rec:
        return ["a_dfki", truth, why or f"ERROR: {rec['error'][:80]}", "", "", "", "", "(no twin)", "?", "NO"], False  # type: ignore[index]
    j = rec["judgement"]
    errors, worse = _errors(rec)
    levels = f"{errors}; held-out MSE {j['error_given']:.3g} given, null level {j['error_null']:.3g}"
    wall = (run / "wall_s").read_text().strip() if (run / "wall_s").exists() else "?"
    named = _named(rec) or "—"
    row = ["a_dfki", truth, rec["verdict"], named, "(no truth)", _tested(rec), levels, "(no twin)", wall]
    return [*row, "reported" if not worse else "NO (fix worse)"], not worse


def main(argv: list[str]) -> int:
    out = Path(argv[0]) if argv else Path("outputs/measured_cases")
    real = real_row(Path(argv[1]) if len(argv) > 1 else out / "a_dfki")
    cases = sorted(p.parent.name for p in (out / "data").glob("*/truth.json"))
    header = [
        "case",
        "truth",
        "verdict",
        "effect named (fitted)",
        "coefficient vs truth",
        "tested on held-out data",
        "held-out rollout RMSE before → after",
        "clean twin: verdict; named; before → after",
        "wall s (recording + twin)",
        "holds",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    held = 0
    if real is not None:
        lines.append("| " + " | ".join(real[0]) + " |")
    for case in cases:
        row, ok = score(out, case)
        held += ok
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", f"{held} of {len(cases)} simulated cases hold."]
    if real is not None:
        lines.append("The real case (a) has no truth to hold to: its row is what the loop measured and said.")
    text = "\n".join(lines)
    (out / "scorecard.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
