"""PySINDy beside `mpsim diagnose` on the visible scorecard cases (issue 61): `mpsim bench bench=peers`.

PySINDy (2.x, the optional extra `pip install 'mpsim[peers]'`, imported only here and only when the suite runs) is
what a user would pick instead of the residual loop. For every case of `cli/diagnose_cases.sh` that has a spec
(`examples/diagnose_cases/`), the suite simulates the data as the recipe does (the same spec, effects, 64
recordings, data seed 0) and keeps the recipe's held-in split (70 %, `split_trajectories` with seed 0). Then:

- **Target.** PySINDy's default derivative estimate (`FiniteDifference()`: second-order central differences,
  one-sided at the ends) minus the nominal model's right-hand side at the observed states, on the dynamic rows
  only (the spec's kinematic rows, x' = v, are not searched, as in the loop). The nominal parameters are the
  fitted ones of the recipe's run (`<runs>/<case>/checkpoints/<case>.ckpt`, the same fit mpsim diagnoses) when
  that checkpoint exists, else the model spec's values (`params=spec`: always the spec's); the `params` column
  says which.
- **Library.** The loop's kinds (`mpsim.diagnose.params.KIND_COMPLEXITY`) less DelayedFeedback, per node with one
  coefficient shared by all nodes, each evaluated by the effect's own `features` (the same signs and units as
  mpsim reports): Bias 1; LinearDamping −s, QuadraticDrag −s|s|, CubicStiffness −s³ and DryFriction −tanh(s/ε)
  (ε as the loop sets it: the data's resolution, never below 1 % of the spread) for every state s;
  DiffusiveCoupling Σ_j(s_j − s_i), SineCoupling Σ_j sin(s_j − s_i), CosineCoupling Σ_j cos(s_j − s_i) where the
  data have a graph; PeriodicForcing sin ωt, cos ωt at the peak of the row's residual periodogram (the mean over
  recordings of each recording's periodogram, Hann window, 16× zero padding). One phase for all recordings: a
  sparse regression on a fixed library has no column per recording.
- **Sparse fit and the threshold rule, fixed before any run.** PySINDy's `STLSQ` (its defaults otherwise:
  alpha 0.05, 20 iterations, unbiased refit) on columns scaled to unit RMS, with threshold = `threshold` (0.05) ×
  the RMS of the row's derivative estimate: a term is kept only if its contribution (coefficient × its column's
  RMS) is at least 5 % of the row's dynamics. (A share of the residual's own scale has no floor: on a clean twin
  the residual is all discretisation error and a share of it is always kept.) The number came from an order-of-
  magnitude estimate before the runs (discretisation and difference errors here are ~1 % of the dynamics, the
  hidden effects ~10 %) and was not tuned afterwards.
- **Judged as the scorecard judges** (`cli/diagnose_cases.sh`'s scorer, `TRUTH` below mirrors it): right means the
  right kind on the right row with the coefficient within the case's bound (10 %; ω 3 % for the drive) and nothing
  else named; on clean twins nothing named; for the effect outside the library nothing named (PySINDy has no
  *unexplained* verdict: naming nothing is its no-claim).

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
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mpsim import effects as fx
from mpsim.bench.common import Suite
from mpsim.data.dataset import split_trajectories
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.library import DRY_MIN_SCALE, evaluate_effect
from mpsim.diagnose.noise import resolution
from mpsim.diagnose.params import KIND_COMPLEXITY
from mpsim.errors import ConfigError
from mpsim.graphs.batch import batch_graph
from mpsim.models.equations import EquationsModel
from mpsim.spec.files import load_spec_file
from mpsim.systems.equations import EquationsSystem
from mpsim.systems.simulation import simulate
from mpsim.training.checkpoint import load_checkpoint

INSTALL = "pip install 'mpsim[peers]'"
#: PySINDy's library: the loop's kinds less DelayedFeedback (a regression at one time has no state history) and
#: ParameterDrift (its column is a model's sensitivity, not a function of the data)
KINDS = tuple(k for k in KIND_COMPLEXITY if k not in ("DelayedFeedback", "ParameterDrift"))
NEEDS_GRAPH = ("DiffusiveCoupling", "SineCoupling", "CosineCoupling")
SPLIT = (0.7, 0.15, 0.15)  # the recipe's data.split: train (held-in) / val / test
UNEXPLAINED = "unexplained"
#: one library candidate: (kind, source state or None, fixed parameters, [B, T, N, K] its columns)
Column = tuple[str, int | None, dict[str, Any], np.ndarray]


@dataclass(frozen=True)
class PeerCase:
    """One scorecard case: how its data are made and what they hold.

    Attributes:
        data, model: the data spec and the nominal model spec (file names in `specs`).
        effects: (kind, arguments) of effects added to the data (the recipe's `system.effects`).
        params: overrides of the data spec's parameters (a clean twin of an effect written into the equations).
        truth: (kind, row, reported key, true value, bound), `UNEXPLAINED` (outside the library) or None (nothing).
        text: the truth as the scorecard writes it.
        recipe: the case is in `cli/diagnose_cases.sh` (its mpsim run can exist).
    """

    data: str
    model: str
    truth: tuple[str, str, str, float, float] | str | None
    text: str
    effects: tuple[tuple[str, dict[str, Any]], ...] = ()
    params: dict[str, Any] = field(default_factory=dict)
    recipe: bool = True


_DAMPING = (("LinearDamping", {"coef": 0.3, "target": "v"}),)
_DRIVE = (
    (
        "PeriodicForcing",
        {"amplitude": 1.5, "omega": 3.1, "phase": 0.0, "target": "v", "random_phase": True, "phase_seed": 0},
    ),
)
_FRICTION = (("DryFriction", {"coef": 0.5, "target": "v", "scale": 0.001}),)
_LAG = -0.4 * math.sin(0.25)
CASES: dict[str, PeerCase] = {
    "a_damped": PeerCase(
        "a_chain_data.yaml",
        "a_chain_model.yaml",
        ("LinearDamping", "v", "coef", 0.3, 0.10),
        "LinearDamping(v) coef 0.3",
        _DAMPING,
    ),
    "a_undamped": PeerCase("a_chain_data.yaml", "a_chain_model.yaml", None, "nothing"),
    "b_vdp": PeerCase(
        "b_vdp_data.yaml",
        "b_vdp_model.yaml",
        ("PeriodicForcing", "v", "omega", 3.1, 0.03),
        "PeriodicForcing(v) omega 3.1, a phase per recording",
        _DRIVE,
    ),
    "b_vdp_clean": PeerCase("b_vdp_data.yaml", "b_vdp_model.yaml", None, "nothing", recipe=False),
    "c_kuramoto_lag": PeerCase(
        "c_kuramoto_lag_data.yaml",
        "c_kuramoto_lag_model.yaml",
        ("CosineCoupling", "theta", "coef", _LAG, 0.10),
        f"CosineCoupling(theta) coef {_LAG:.4g}",
    ),
    "c_kuramoto_clean": PeerCase(
        "c_kuramoto_lag_data.yaml",
        "c_kuramoto_lag_model.yaml",
        None,
        "nothing",
        params={"alpha": 0.0},
        recipe=False,
    ),
    "d_chain_friction": PeerCase(
        "d_chain_friction_data.yaml",
        "d_chain_friction_model.yaml",
        ("DryFriction", "v", "coef", 0.5, 0.10),
        "DryFriction(v) coef 0.5",
        _FRICTION,
    ),
    "d_chain_clean": PeerCase(
        "d_chain_friction_data.yaml", "d_chain_friction_model.yaml", None, "nothing", recipe=False
    ),
    "e_pendulum_sin2": PeerCase(
        "e_pendulum_sin2_data.yaml", "e_pendulum_sin2_model.yaml", UNEXPLAINED, "sin 2θ torque (outside the library)"
    ),
    "e_pendulum_clean": PeerCase(
        "e_pendulum_sin2_data.yaml", "e_pendulum_sin2_model.yaml", None, "nothing", params={"b": 0.0}, recipe=False
    ),
}
#: the cases of the recipe, and the clean twins only PySINDy runs (`twins=true`)
RECIPE_CASES = [name for name, case in CASES.items() if case.recipe]
EXTRA_TWINS = [name for name, case in CASES.items() if not case.recipe]


def require_pysindy() -> Any:
    """The `pysindy` module, or one clear message naming the extra that installs it."""
    try:
        import pysindy  # type: ignore[import-not-found, import-untyped, unused-ignore]
    except ImportError:
        raise ConfigError(
            f"bench=peers runs PySINDy beside mpsim, and pysindy is not installed: {INSTALL} "
            "(or pip install 'pysindy>=2')."
        ) from None
    return pysindy


# ---- data and the nominal model -----------------------------------------------------------------------------
def simulate_case(case: PeerCase, specs: Path, n: int = 64, seed: int = 0) -> Trajectories:
    """The recipe's recordings of `case` (float64), held-in split only (the records mpsim fits on)."""
    spec = load_spec_file(specs / case.data)
    spec["params"] = {**spec.get("params", {}), **case.params}
    effects = [getattr(fx, kind)(**args) for kind, args in case.effects]
    system = EquationsSystem(spec=spec, effects=effects)
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


@torch.no_grad()
def nominal_rhs(model: EquationsModel, data: Trajectories) -> np.ndarray:
    """[B, T, N, D] the nominal model's right-hand side at every observed state and time."""
    b, n_t, n, d = data.x.shape
    x = data.x.double().reshape(b * n_t, n, d)
    t = data.t.double()[None, :].expand(b, n_t).reshape(b * n_t, 1)
    ei = data.edge_index if data.shared_graph else data.edge_index.repeat_interleave(n_t, dim=0)
    graph = batch_graph(ei, b * n_t, n, dtype=torch.float64) if data.edge_index.numel() else None
    values = {k: v.detach().double() for k, v in model.parameters_now().items()}
    return model.field(t, x, values, graph).reshape(b, n_t, n, d).numpy()


# ---- PySINDy's side ----------------------------------------------------------------------------------------
def periodogram_peak(r: np.ndarray, t: np.ndarray, pad: int = 16) -> float:
    """Angular frequency of the peak of the mean per-recording periodogram of r: [B, T, N] (node-averaged)."""
    signal = r.mean(axis=2)
    signal = signal - signal.mean(axis=1, keepdims=True)
    n_t = signal.shape[1]
    power = np.abs(np.fft.rfft(signal * np.hanning(n_t), n=pad * n_t, axis=1)) ** 2
    freqs = 2 * math.pi * np.fft.rfftfreq(pad * n_t, d=float(t[1] - t[0]))
    lowest = 2 * pad  # skip the window's main lobe at zero frequency (as the loop does)
    return float(freqs[lowest + int(np.argmax(power.mean(axis=0)[lowest:]))])


def library(data: Trajectories, omega: float) -> list[Column]:
    """(kind, source, fixed parameters, [B, T, N, K] columns) of every candidate, by the effects' own features."""
    d = data.state_dim
    has_edges = data.edge_index.numel() > 0 and bool((data.edge_index >= 0).any())
    eps = torch.maximum(resolution(data.x), DRY_MIN_SCALE * data.x.double().reshape(-1, d).std(0))
    out: list[tuple[str, int | None, dict[str, Any], fx.Effect]] = []
    for kind in KINDS:
        if kind in NEEDS_GRAPH and not has_edges:
            continue
        cls = getattr(fx, kind)
        if kind == "Bias":
            out.append((kind, None, {}, cls(0.0, target=0)))
        elif kind == "PeriodicForcing":
            out.append((kind, None, {"omega": omega}, cls(0.0, omega=omega, target=0)))
        else:
            for s in range(d):
                extra = {"scale": float(eps[s])} if kind == "DryFriction" else {}
                out.append((kind, s, extra, cls(0.0, target=0, source=s, **extra)))
    return [(k, s, p, evaluate_effect(e.bind(data.state_names), data).detach().numpy()) for k, s, p, e in out]


def _label(kind: str, source: int | None, params: dict[str, Any], names: list[str], row: str) -> str:
    inside = names[source] if source is not None else (f"ω={params['omega']:.4g}" if "omega" in params else "")
    return f"d{row}/dt: {kind}({inside})" if inside else f"d{row}/dt: {kind}"


def sparse_fit(
    ps: Any,
    columns: list[Column],
    y: np.ndarray,
    threshold: float,
    names: list[str],
    row: str,
) -> list[dict[str, Any]]:
    """STLSQ of y: [M] on the columns (each [M, K] flattened, scaled to unit RMS); the kept candidates, named."""
    blocks = [c[3].reshape(y.size, -1) for c in columns]
    theta = np.concatenate(blocks, axis=1)
    scale = np.sqrt((theta**2).mean(axis=0))
    usable = scale > 1e-12 * max(float(scale.max()), 1e-300)  # a graph sum on a graph without edges is all zero
    opt = ps.STLSQ(threshold=threshold)
    with warnings.catch_warnings():  # "eliminated all coefficients" is PySINDy's no-claim, reported as such
        warnings.simplefilter("ignore", UserWarning)
        opt.fit(theta[:, usable] / scale[usable], y[:, None])
    coef = np.zeros(theta.shape[1])
    coef[usable] = opt.coef_[0] / scale[usable]
    named, start = [], 0
    for (kind, source, params, _), block in zip(columns, blocks, strict=True):
        c = coef[start : start + block.shape[1]]
        start += block.shape[1]
        if not np.any(c != 0):
            continue
        values = {"amplitude": float(np.hypot(*c)), "omega": params["omega"]} if len(c) == 2 else {"coef": float(c[0])}
        named.append({"kind": kind, "row": row, "label": _label(kind, source, params, names, row), "values": values})
    return named


def pysindy_side(data: Trajectories, model: EquationsModel, threshold: float = 0.05) -> tuple[list[dict], float]:
    """(the candidates PySINDy names on the dynamic rows, its wall time in seconds) for `data` and the nominal
    `model` (see the module docstring: target, library, threshold rule)."""
    ps = require_pysindy()
    start = time.perf_counter()
    b, n_t, n, d = data.x.shape
    x = data.x.double().numpy()
    t = data.t.double().numpy()
    xdot = ps.FiniteDifference(axis=1)(x.reshape(b, n_t, n * d), t).reshape(b, n_t, n, d)
    residual = xdot - nominal_rhs(model, data)
    names = list(data.state_names)
    named: list[dict] = []
    for i, row in enumerate(names):
        if row in model.kinematic_states:
            continue
        columns = library(data, periodogram_peak(residual[..., i], t))
        rule = threshold * float(np.sqrt((xdot[..., i] ** 2).mean()))
        named += sparse_fit(ps, columns, residual[..., i].reshape(-1), rule, names, row)
    return named, time.perf_counter() - start


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
        {"kind": e["kind"], "row": e["label"].split("/dt")[0][1:], "label": e["label"], "values": e["values"]}
        for e in r["effects_named"]
    ]
    before, after = r["before"]["rollout_rmse"], (r.get("after") or {}).get("rollout_rmse")
    worse = after is not None and after > before
    return {"named": named, "verdict": r["verdict"], "worse": worse, "seconds": seconds}


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
        twins: also run PySINDy on the clean twins the recipe lacks (b_vdp, c, d and e without their effect).
        runs: a folder of finished `cli/diagnose_cases.sh` runs (its `OUT`): the mpsim column and the fitted
            nominal parameters; a case without a run says *not run* (the loop is never run here).
        specs: the folder of the cases' data and model specs.
        n, seed: recordings simulated per case and their data seed (the recipe's `n=64`, `data.seed=0`).
        threshold: STLSQ's threshold as a share of the RMS of the row's derivative estimate (on unit-RMS columns).
        params: the nominal parameters PySINDy's target subtracts: `fitted` (the recipe's fit, from `runs`, where
            a run exists; else the spec's) or `spec` (always the model spec's values).
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
    ) -> None:
        chosen = list(cases) if cases is not None else list(RECIPE_CASES)
        unknown = [c for c in chosen if c not in CASES]
        if unknown:
            raise ConfigError(f"bench.cases: unknown case(s) {unknown}; choose from {list(CASES)}.")
        if not 0 < threshold < 1:
            raise ConfigError(f"bench.threshold must be a share in (0, 1); got {threshold}.")
        if params not in ("fitted", "spec"):
            raise ConfigError(f"bench.params must be fitted or spec; got {params!r}.")
        self.params = params
        self.cases = chosen + ([c for c in EXTRA_TWINS if c not in chosen] if twins else [])
        self.runs, self.specs = Path(runs), Path(specs)
        self.n, self.seed, self.threshold = int(n), int(seed), float(threshold)
        if not (self.specs / CASES[self.cases[0]].data).is_file():
            raise ConfigError(
                f"bench.specs={specs}: no {CASES[self.cases[0]].data} there; give the folder of the scorecard's "
                "specs (examples/diagnose_cases in the repository), relative to where mpsim is started."
            )

    def run(self) -> list[dict[str, Any]]:
        require_pysindy()  # one message before any simulation
        return [self._row(name) for name in self.cases]

    def _row(self, name: str) -> dict[str, Any]:
        case = CASES[name]
        data = simulate_case(case, self.specs, self.n, self.seed)
        fitted = case.recipe and self.params == "fitted"
        ckpt = self.runs / name / "checkpoints" / f"{name}.ckpt" if fitted else None
        model, params = nominal_model(case, self.specs, ckpt, data.state_dim)
        named, seconds = pysindy_side(data, model, self.threshold)
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
        clean = [r for r in rows if r["truth"] == "nothing"]
        ran = [r for r in clean if r["mpsim right"]]
        bugs = [r["case"] for r in rows if r["PySINDy right"] == "yes" and r["mpsim right"] == "NO"]
        return [
            f"Threshold rule (fixed in advance): STLSQ on unit-RMS columns, threshold {self.threshold:g} × the RMS of "
            "the row's derivative estimate (a term must carry that share of the row's dynamics).",
            f"False claims on clean twins: PySINDy {sum(r['PySINDy right'] != 'yes' for r in clean)} of {len(clean)}; "
            f"mpsim {sum(r['mpsim right'] != 'yes' for r in ran)} of {len(ran)} (the recipe's twins with a run).",
            "PySINDy right where mpsim is not (bugs to fix): " + (", ".join(bugs) if bugs else "none") + ".",
        ]
