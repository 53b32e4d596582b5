"""ODE integration for models (torchdiffeq wrapper) and least-squares MNN solvers."""

from mpsim.solvers.odeint import ODESolver as ODESolver
