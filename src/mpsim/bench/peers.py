"""PySINDy beside `mpsim diagnose` on the visible scorecard cases (issue 61): `mpsim bench bench=peers`.

PySINDy (2.x, the optional extra `pip install 'mpsim[peers]'`, imported only here and only when the suite runs) is
what a user would pick instead of the residual loop. For every case of `peers_cases.CASES` (those of
`cli/diagnose_cases.sh`, one line each with its truth) whose specs are in `examples/diagnose_cases/`, the suite
simulates the data as the recipe does (the same spec, effects, 64 recordings, data seed 0) and keeps the recipe's
held-in split (70 %, `split_trajectories` with seed 0). A case whose spec files are not there says *spec missing*;
one whose truth or effects are still `TODO` says *truth TODO*. Then (`peers_library`):

- **Target.** PySINDy's default derivative estimate (`FiniteDifference()`: second-order central differences,
  one-sided at the ends) minus the nominal model's right-hand side at the observed states, on the dynamic rows
  only (the spec's kinematic rows, x' = v, are not searched, as in the loop). The nominal parameters are the
  fitted ones of the recipe's run (`<runs>/<case>/checkpoints/<case>.ckpt`, the same fit mpsim diagnoses) when
  that checkpoint exists, else the model spec's values (`params=spec`: always the spec's); the `params` column
  says which.
- **Library, extended as an exploring user extends it** (one coefficient per term, shared by all nodes; each
  column evaluated by the effect's own `features`, so the signs and units are those mpsim reports):
  Bias 1; LinearDamping −s, QuadraticDrag −s|s|, CubicStiffness −s³ and DryFriction −tanh(s/ε) (ε as the loop
  sets it) for every state s; on a graph DiffusiveCoupling Σ_j(s_j − s_i) and the phase couplings
  Σ_j sin(k(s_j − s_i)), Σ_j cos(k(s_j − s_i)) at harmonics k = 1, 2, 3; PeriodicForcing sin ωt, cos ωt at the
  peak of the row's residual periodogram (mean per-recording periodogram, Hann window, 16× zero padding; one phase
  for all recordings: a fixed library has no column per recording); delayed copies s(t − m·dt), m = 1, 2, 4, 8
  (DelayedFeedback's +c·s(t − τ): PySINDy sees a delay only on the sampling grid, and the first 8 samples of each
  recording, which have none, are left out of the fit); t-modulated terms t, −t·s, −t·s|s|, −t·s³, −t·tanh(s/ε);
  the nominal model's physical terms modulated by t, t·p·∂f_row/∂p for each learnable scalar p (how a user finds a
  drift of g/l through t·sin θ: named ParameterDrift(p), its coefficient the rate s of p·(1 + s·t)), and
  t·f_row, the row's whole nominal right-hand side. A column parallel to an earlier one is left out (a drifting
  stiffness's t·k·x is −k × t·(−x)).
- **Sparse fit and the threshold rule, fixed before any run and not re-tuned for the extended library.** PySINDy's
  `STLSQ` (its defaults otherwise: alpha 0.05, 20 iterations, unbiased refit) on columns scaled to unit RMS, with
  threshold = `threshold` (0.05) × the RMS of the row's derivative estimate: a term is kept only if its
  contribution (coefficient × its column's RMS) is at least 5 % of the row's dynamics. (A share of the residual's
  own scale has no floor: on a clean twin the residual is all discretisation error and a share of it is always
  kept.) The number came from an order-of-magnitude estimate before the first runs (discretisation and difference
  errors here are ~1 % of the dynamics, the hidden effects ~10 %).
- **Judged as the scorecard judges** (`cli/diagnose_cases.sh`'s scorer; `peers_cases.CASES` mirrors its `TRUTH`):
  right means the right kind (a harmonic k > 1 in the kind: "SineCoupling(k=2)"; every t-modulated term but
  ParameterDrift is a kind no truth holds) on the right row with the reported value within the case's bound
  (10 %: coef, delay or rate; ω 3 % for a drive) and nothing else named; on clean twins nothing named; for the
  effect outside the library nothing named (PySINDy has no *unexplained* verdict: naming nothing is its no-claim).

The mpsim column reads finished runs of the recipe (`runs=`, e.g. `OUT=outputs/diagnose_cases` of
`cli/diagnose_cases.sh`: `<case>/diagnose/diagnosis.json`, `<case>/wall_s`) and says *not run* where there is none:
the suite never runs the loop itself. Wall times: PySINDy's is the derivative, library and fit of the held-in
records (the simulation and the nominal fit it borrows are not counted); mpsim's is the recipe's whole case
(simulate, fit the nominal model, diagnose with `fix=true`). With `twins=true` PySINDy also runs on clean twins
the recipe lacks (each case's data without its effect, nominal parameters = the truth's); their mpsim column says
*not in the recipe*.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from mpsim.bench.common import Suite
from mpsim.bench.peers_cases import CASES, EXTRA_TWINS, RECIPE_CASES, TODO, UNEXPLAINED, PeerCase
from mpsim.bench.peers_library import EXTENSIONS, INSTALL, nominal_rhs, pysindy_side, require_pysindy
from mpsim.data.dataset import split_trajectories
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError
from mpsim.models.equations import EquationsModel
from mpsim.spec.files import load_spec_file
from mpsim.systems.equations import EquationsSystem
from mpsim.systems.simulation import simulate
from mpsim.training.checkpoint import load_checkpoint

__all__ = [
    "CASES",
    "EXTRA_TWINS",
    "INSTALL",
    "RECIPE_CASES",
    "TODO",
    "UNEXPLAINED",
    "PeerCase",
    "PeersBench",
    "judge",
    "mpsim_side",
    "nominal_rhs",
    "pysindy_side",
    "require_pysindy",
]
SPLIT = (0.7, 0.15, 0.15)  # the recipe's data.split: train (held-in) / val / test


def simulate_case(case: PeerCase, specs: Path, n: int = 64, seed: int = 0) -> Trajectories:
    """The recipe's recordings of `case` (float64), held-in split only (the records mpsim fits on)."""
    spec = load_spec_file(specs / case.data)
    spec["params"] = {**spec.get("params", {}), **case.params}
    system = EquationsSystem(spec=spec, effects=case.make_effects())
    data = simulate(system, n, seed=seed)
    return split_trajectories(data, SPLIT, seed=seed).train


def nominal_model(case: PeerCase, specs: Path, ckpt: Path | None, state_dim: int) -> tuple[EquationsModel, str]:
    """(the nominal model, "fitted" or "spec"): the recipe's fitted parameters when `ckpt` exists."""
    model = EquationsModel(state_dim, spec=load_spec_file(specs / case.model))
    if ckpt is None or not ckpt.is_file():
        return model, "spec"
    state = load_checkpoint(ckpt)["model"]["state_dict"]
    model.load_state_dict({k: v for k, v in state.items() if k.startswith("raw.")}, strict=False)
    return model, "fitted"


# ---- mpsim's side and the judgement --------------------------------------------------------------------------
def mpsim_side(run: Path) -> dict[str, Any] | None:
    """What the recipe's run of a case named (None: no finished run): named, verdict, worse, wall time."""
    path = run / "diagnose" / "diagnosis.json"
    if not path.is_file():
        return None
    r = json.loads(path.read_text())
    wall = run / "wall_s"
    seconds = float(wall.read_text().strip()) if wall.is_file() else math.nan
    if "error" in r:
        return {"named": [], "verdict": "ERROR " + str(r["error"])[:60], "worse": False, "seconds": seconds}
    named = [
        {"kind": kind_of(e), "row": e["label"].split("/dt")[0][1:], "label": e["label"], "values": e["values"]}
        for e in r["effects_named"]
    ]
    before, after = r["before"]["rollout_rmse"], (r.get("after") or {}).get("rollout_rmse")
    worse = after is not None and after > before
    return {"named": named, "verdict": r["verdict"], "worse": worse, "seconds": seconds}


def kind_of(effect: dict[str, Any]) -> str:
    """A named effect's kind as the scorecard writes it, its harmonic k > 1 included ("SineCoupling(k=2)")."""
    k = (effect.get("effect") or {}).get("harmonic", 1)
    return effect["kind"] if k == 1 else f"{effect['kind']}(k={k})"


def judge(case: PeerCase, named: list[dict], verdict: str | None = None, worse: bool = False) -> tuple[bool, str]:
    """(right?, coefficient error) by the scorecard's rule; `verdict` None: a tool without one (no name = no claim)."""
    if case.truth is None:
        return not named and not worse, ""
    if case.truth == UNEXPLAINED:
        held = not named if verdict is None else verdict == "unexplained structured residual"
        return held and not worse, ""
    if not isinstance(case.truth, tuple):
        raise ValueError(f"unknown truth {case.truth!r}")
    kind, row, key, value, bound = case.truth
    hits = [e for e in named if e["kind"] == kind and e["row"] == row]
    if not hits:
        return False, ""
    rel = abs(hits[0]["values"][key] - value) / abs(value)
    return rel <= bound and len(named) == 1 and not worse, f"{rel:.2%}"


def describe(named: list[dict]) -> str:
    """The named effects as the scorecard writes them: `dv/dt: LinearDamping(v) (coef 0.2955)`."""
    parts = [f"{e['label']} ({', '.join(f'{k} {v:.4g}' for k, v in e['values'].items())})" for e in named]
    return "; ".join(parts) or "—"


# ---- the suite ---------------------------------------------------------------------------------------------
class PeersBench(Suite):
    """PySINDy and `mpsim diagnose` side by side on the scorecard's spec cases (one row per case).

    Args:
        cases: scorecard cases (null: every case of the recipe with a spec).
        twins: also run PySINDy on the clean twins the recipe lacks (b_vdp, c, d, e, f without their effect).
        runs: a folder of finished `cli/diagnose_cases.sh` runs (its `OUT`): the mpsim column and the fitted
            nominal parameters; a case without a run says *not run* (the loop is never run here).
        specs: the folder of the cases' data and model specs.
        n, seed: recordings simulated per case and their data seed (the recipe's `n=64`, `data.seed=0`).
        threshold: STLSQ's threshold as a share of the RMS of the row's derivative estimate (on unit-RMS columns).
        params: the nominal parameters PySINDy's target subtracts: `fitted` (the recipe's fit, from `runs`, where
            a run exists; else the spec's) or `spec` (always the model spec's values).
        extend: the families of terms added to the loop's kinds (null: all of `EXTENSIONS`: delays, time,
            harmonics; [] the loop's kinds alone, first harmonics only).
    """

    name = "peers"

    def __init__(
        self,
        cases: list[str] | None = None,
        twins: bool = True,
        runs: str = "outputs/diagnose_cases",
        specs: str = "examples/diagnose_cases",
        n: int = 64,
        seed: int = 0,
        threshold: float = 0.05,
        params: str = "fitted",
        extend: list[str] | None = None,
    ) -> None:
        chosen = list(cases) if cases is not None else list(RECIPE_CASES)
        unknown = [c for c in chosen if c not in CASES]
        if unknown:
            raise ConfigError(f"bench.cases: unknown case(s) {unknown}; choose from {list(CASES)}.")
        if not 0 < threshold < 1:
            raise ConfigError(f"bench.threshold must be a share in (0, 1); got {threshold}.")
        if params not in ("fitted", "spec"):
            raise ConfigError(f"bench.params must be fitted or spec; got {params!r}.")
        self.extend = tuple(EXTENSIONS if extend is None else extend)
        if set(self.extend) - set(EXTENSIONS):
            raise ConfigError(f"bench.extend: {list(self.extend)}; choose among {list(EXTENSIONS)} ([]: none).")
        self.params = params
        self.cases = chosen + ([c for c in EXTRA_TWINS if c not in chosen] if twins else [])
        self.runs, self.specs = Path(runs), Path(specs)
        self.n, self.seed, self.threshold = int(n), int(seed), float(threshold)
        if all(CASES[c].missing(self.specs) for c in self.cases):
            raise ConfigError(
                f"bench.specs={specs}: none of the cases' specs ({CASES[self.cases[0]].data}, ...) is there; give "
                "the folder of the scorecard's specs (examples/diagnose_cases in the repository), relative to "
                "where mpsim is started."
            )

    def run(self) -> list[dict[str, Any]]:
        require_pysindy()  # one message before any simulation
        return [self._row(name) for name in self.cases]

    def _row(self, name: str) -> dict[str, Any]:
        case = CASES[name]
        missing, why = case.missing(self.specs), ""
        if missing or case.todo:
            why = f"spec missing: {', '.join(missing)}" if missing else "truth TODO (peers_cases.CASES)"
        if why:
            return {
                "case": name if case.recipe else f"{name} (twin, PySINDy only)",
                "truth": case.text,
                "PySINDy named (fitted)": why,
                "PySINDy error": "",
                "PySINDy right": "",
                "PySINDy s": math.nan,
                "params": "",
                "mpsim named (fitted)": "",
                "mpsim error": "",
                "mpsim right": "",
                "mpsim s": math.nan,
            }
        data = simulate_case(case, self.specs, self.n, self.seed)
        fitted = case.recipe and self.params == "fitted"
        ckpt = self.runs / name / "checkpoints" / f"{name}.ckpt" if fitted else None
        model, params = nominal_model(case, self.specs, ckpt, data.state_dim)
        named, seconds = pysindy_side(data, model, self.threshold, self.extend)
        right, err = judge(case, named)
        row: dict[str, Any] = {
            "case": name if case.recipe else f"{name} (twin, PySINDy only)",
            "truth": case.text,
            "PySINDy named (fitted)": describe(named),
            "PySINDy error": err,
            "PySINDy right": "yes" if right else "NO",
            "PySINDy s": round(seconds, 2),
            "params": params,
        }
        mine = mpsim_side(self.runs / name) if case.recipe else None
        if mine is None:
            why = "not run" if case.recipe else "not in the recipe"
            return {**row, "mpsim named (fitted)": why, "mpsim error": "", "mpsim right": "", "mpsim s": math.nan}
        ok, mine_err = judge(case, mine["named"], mine["verdict"], mine["worse"])
        text = describe(mine["named"]) if mine["named"] else mine["verdict"]
        return {
            **row,
            "mpsim named (fitted)": text,
            "mpsim error": mine_err,
            "mpsim right": "yes" if ok else "NO",
            "mpsim s": mine["seconds"],
        }

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        clean = [r for r in rows if r["truth"] == "nothing" and r["PySINDy right"]]
        ran = [r for r in clean if r["mpsim right"]]
        judged = [r for r in rows if r["PySINDy right"]]
        both = [r for r in judged if r["mpsim right"]]
        bugs = [r["case"] for r in rows if r["PySINDy right"] == "yes" and r["mpsim right"] == "NO"]
        return [
            f"Threshold rule (fixed in advance): STLSQ on unit-RMS columns, threshold {self.threshold:g} × the RMS of "
            "the row's derivative estimate (a term must carry that share of the row's dynamics). Library: the loop's "
            f"kinds + {', '.join(self.extend) or 'nothing'}.",
            f"False claims on clean twins: PySINDy {sum(r['PySINDy right'] != 'yes' for r in clean)} of {len(clean)}; "
            f"mpsim {sum(r['mpsim right'] != 'yes' for r in ran)} of {len(ran)} (the recipe's twins with a run).",
            f"Right: PySINDy {sum(r['PySINDy right'] == 'yes' for r in judged)} of {len(judged)} rows; mpsim "
            f"{sum(r['mpsim right'] == 'yes' for r in both)} of {len(both)} (the rows with a run); "
            f"{len(rows) - len(judged)} rows not judged (spec missing or truth TODO).",
            "PySINDy right where mpsim is not (bugs to fix): " + (", ".join(bugs) if bugs else "none") + ".",
        ]
