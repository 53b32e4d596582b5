"""Equations written as text (a *spec*): a spec of states, right-hand sides and parameters, parsed safely into sympy and
compiled to vectorised torch code over batch × nodes × edges.

A spec is plain data (a YAML file or the same keys inline in a config)::

    states: [theta, omega]                 # per node, in the data's column order
    inputs: [tau]                          # optional: per-node inputs the data give (its controls, by name)
    equations:                             # d(state)/dt, one expression per state
      theta: omega
      omega: (tau - b*omega)/(m*l^2) - (g/l)*sin(theta) - k*sum_nbr(theta - theta_j)
    params: {g: 9.81, l: 1.5, k: 2.0, m: 1.0, b: 0.1}   # scalar, per-node list (length N), or matrix [N·D, N·D]
    learnable: [g, k]                      # what training fits (default: every parameter)
    shift_boundary: 0.0                    # what shift(x, k) reads beyond the ends: wrap | edge | a number

Expressions use + - * / ** (or ^), numbers, `pi`, the functions sin cos tan exp log sqrt abs sign tanh, `t`
(absolute time), the node's own states, inputs and parameters by name, and neighbour terms over the data's graph:
`sum_nbr(e)` / `mean_nbr(e)` evaluate `e` on every edge j → i, where `x_j` is the neighbour's value of state,
input (or per-node parameter) `x` and a plain `x` the receiving node's own; `deg` is a node's in-degree; `lin(H)` is
this node's and this state's entry of H·vec(X) with X the [N, D] node states flattened node-major; `shift(x, k)` is
state, input or per-node parameter `x` at node i + k in the node order (k a whole number), beyond the ends as
`shift_boundary` says: `wrap` (mod N; the default when the spec's graph is `ring`), `edge` (the end node's value) or
a number.

Nothing in a spec is executed: expressions are read with Python's `ast` parser, every node is checked against
the grammar above and then rebuilt as a sympy expression, which is compiled once into a tree of torch
operations. Subexpressions that recur are evaluated once per call; a sub-term of a neighbour sum that reads
only one end of the edge is evaluated per node and gathered, so `sin(theta_j)` costs one `sin` per node.

The package: `files` reads a spec file, `grammar` parses expressions, `parse` checks a spec, `field` compiles it.
"""

from mpsim.spec.field import EquationField as EquationField
from mpsim.spec.files import load_spec_file as load_spec_file
from mpsim.spec.parse import MODEL_KEYS as MODEL_KEYS
from mpsim.spec.parse import SYSTEM_KEYS as SYSTEM_KEYS
from mpsim.spec.parse import Spec as Spec
from mpsim.spec.parse import check_nodes as check_nodes
from mpsim.spec.parse import check_states as check_states
from mpsim.spec.parse import merge_spec as merge_spec
from mpsim.spec.parse import parse_spec as parse_spec
