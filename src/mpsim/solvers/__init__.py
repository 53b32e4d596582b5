"""ODE integration for models (torchdiffeq wrapper) and the least-squares MNN / S-MNN solvers."""

from mpsim.solvers.mnn_dense import dense_solve as dense_solve
from mpsim.solvers.mnn_dense import mnn_dense_solve as mnn_dense_solve
from mpsim.solvers.odeint import ODESolver as ODESolver
from mpsim.solvers.smnn import SolverError as SolverError
from mpsim.solvers.smnn import smnn_solve as smnn_solve
