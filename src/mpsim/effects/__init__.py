"""Named physical effects: extra terms `dx_target/dt += Σ_k c_k φ_k(t, x, neighbours)` with learnable c.

The same objects shape ground-truth data (a system's `effects=[...]`, e.g. hidden damping in a test set),
sit inside models with learnable coefficients (`model.effects=[...]`), and form the candidate library of the
residual loop (`mpsim diagnose`), which regresses a model's residual on their basis functions `features`.

Each effect acts on one state variable of every node (`target`) and reads one (`source`, default the
target); both can be given by name (``omega``) and are resolved against the state names with `bind`.
Coefficients are in the data's raw units per unit time. A single-basis state term (`PER_NODE_KINDS`) may act on
some nodes only, with a coefficient each: `nodes=[2]` (or `[0, 2]`) and `coef` one value per listed node, e.g.
`LinearDamping(coef=[0.3], nodes=[2], target=omega)`: damping of node 2 alone (zero on the others).

| effect | term added to d(target)/dt |
|---|---|
| `LinearDamping(c)` | −c·s |
| `QuadraticDrag(c)` | −c·s·abs(s) |
| `DryFriction(c, ε)` | −c·tanh(s/ε)  (Coulomb friction, sign(s) smoothed over ε) |
| `CubicStiffness(c)` | −c·s³ |
| `Bias(c)` | c |
| `PeriodicForcing(A, ω, φ)` | A·sin(ω t + φ)  (`random_phase=true`: A·sin(ω t + φ + φ_b), φ_b per trajectory) |
| `DiffusiveCoupling(c)` | c·Σ_j A_ij (s_j − s_i) |
| `SineCoupling(c, k)` | c·Σ_j A_ij sin(k(s_j − s_i))  (phase oscillators; `harmonic` k = 1 by default) |
| `CosineCoupling(c, k)` | c·Σ_j A_ij cos(k(s_j − s_i))  (with `SineCoupling`: a phase lag α; k as above) |
| `DelayedFeedback(c, τ)` | c·s(t − τ) |
| `ParameterDrift(p, s)` | the model's parameter p becomes p·(1 + s·t)  (`model=equations` only) |
| `InputGain(u, g_b)` | the input u reaches the system as g_b·u, a gain per recording b  (`model=equations` only) |
| `DeadZone(u, w)` | the input u reaches the system as sign(u)·max(abs(u) − w, 0)  (`model=equations` only) |
| `InputSaturation(u, U)` | the input u reaches the system as clip(u, −U, U)  (`model=equations` only) |

with s the source variable of node i and A the coupling graph. A phase lag in Kuramoto coupling is the pair
`SineCoupling` + `CosineCoupling`: K·sin(s_j − s_i − α) = K cos α·sin(s_j − s_i) − K sin α·cos(s_j − s_i).

The classes live in `mpsim.effects.base` (the base class and state terms), `mpsim.effects.temporal` (time and
delay terms) and `mpsim.effects.couplings` (neighbour couplings); configs name them here, `_target_: mpsim.effects.<Name>`.
"""

from mpsim.effects.base import (
    PER_NODE_KINDS,
    Bias,
    CubicStiffness,
    DryFriction,
    Effect,
    EffectContext,
    LinearDamping,
    QuadraticDrag,
    total,
)
from mpsim.effects.couplings import CosineCoupling, DiffusiveCoupling, SineCoupling
from mpsim.effects.inputs import DeadZone, InputGain, InputSaturation
from mpsim.effects.temporal import DelayedFeedback, ParameterDrift, PeriodicForcing, max_delay, min_delay

__all__ = [
    "Bias",
    "CosineCoupling",
    "CubicStiffness",
    "DeadZone",
    "DelayedFeedback",
    "DiffusiveCoupling",
    "DryFriction",
    "Effect",
    "EffectContext",
    "InputGain",
    "InputSaturation",
    "LinearDamping",
    "PER_NODE_KINDS",
    "ParameterDrift",
    "PeriodicForcing",
    "QuadraticDrag",
    "SineCoupling",
    "max_delay",
    "min_delay",
    "total",
]
