"""The spec parser and compiler (`mpsim.equations`): safe parsing, clear refusals, exact values, autograd."""

from __future__ import annotations

import math
import re

import pytest
import sympy
import torch

from mpsim.errors import ConfigError
from mpsim.graphs.batch import batch_graph
from mpsim.graphs.topology import make_topology
from mpsim.spec import EquationField, load_spec_file, parse_spec

PENDULUM = {
    "states": ["theta", "omega"],
    "equations": {"theta": "omega", "omega": "-(g/l)*sin(theta) - k*sum_nbr(theta - theta_j)"},
    "params": {"g": 9.81, "l": 1.5, "k": 2.0},
    "learnable": ["g", "k"],
}


def _spec(**changes):
    spec = {**PENDULUM, **changes}
    return parse_spec(spec)


def _eval(spec, x, edge_index, t=0.0, params=None):
    graph = batch_graph(edge_index, x.shape[0], x.shape[1], dtype=x.dtype)
    values = {k: v.to(x) for k, v in spec.params.items()} if params is None else params
    return EquationField(spec)(torch.tensor(t, dtype=x.dtype), x, values, graph)


def test_values_match_a_hand_written_field():
    spec = _spec()
    ei = make_topology("ring", 5)
    x = torch.randn(3, 5, 2, dtype=torch.float64)
    theta, omega = x[..., 0], x[..., 1]
    nbr = torch.zeros_like(theta).index_add_(1, ei[1], theta[:, ei[0]])
    deg = torch.zeros(5, dtype=torch.float64).index_add_(0, ei[1], torch.ones(ei.shape[1], dtype=torch.float64))
    expected = torch.stack([omega, -(9.81 / 1.5) * torch.sin(theta) - 2.0 * (deg * theta - nbr)], -1)
    assert torch.allclose(_eval(spec, x, ei), expected, atol=1e-13)
    assert spec.kinematic == ("theta",)


def test_functions_time_degree_mean_and_per_node_parameters():
    spec = parse_spec(
        {
            "states": ["a"],
            "equations": {
                "a": "tanh(a) + abs(a)*sign(a) + exp(-a**2)/sqrt(2 + cos(a)) + log(2 + tan(a/10)) "
                "+ p*sin(3*t) + deg + mean_nbr(p_j*a_j - a) + 2^2"
            },
            "params": {"p": [0.5, 1.0, 2.0, -1.0]},
        }
    )
    ei = make_topology("chain", 4)
    x = torch.randn(2, 4, 1, dtype=torch.float64)
    a = x[..., 0]
    p = torch.tensor([0.5, 1.0, 2.0, -1.0], dtype=torch.float64)
    deg = torch.tensor([1.0, 2.0, 2.0, 1.0], dtype=torch.float64)
    mean = (torch.zeros_like(a).index_add_(1, ei[1], (p * a)[:, ei[0]]) - deg * a) / deg
    t = 0.7
    expected = (
        torch.tanh(a)
        + a.abs() * a.sign()
        + torch.exp(-(a**2)) / torch.sqrt(2 + torch.cos(a))
        + torch.log(2 + torch.tan(a / 10))
        + p * math.sin(3 * t)
        + deg
        + mean
        + 4
    )
    assert torch.allclose(_eval(spec, x, ei, t=t)[..., 0], expected, atol=1e-12)


def test_matrix_parameter_through_lin_is_node_major():
    n, d = 3, 2
    h = torch.randn(n * d, n * d, dtype=torch.float64)
    spec = parse_spec(
        {"states": ["u", "v"], "equations": {"u": "lin(H)", "v": "-v + lin(H)"}, "params": {"H": h.tolist()}}
    )
    assert spec.n_nodes == 3
    x = torch.randn(4, n, d, dtype=torch.float64)
    hx = (x.reshape(4, n * d) @ h.T).reshape(4, n, d)
    out = _eval(spec, x, torch.zeros(2, 0, dtype=torch.long))
    assert torch.allclose(out[..., 0], hx[..., 0], atol=1e-13)
    assert torch.allclose(out[..., 1], -x[..., 1] + hx[..., 1], atol=1e-13)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_autograd_reaches_every_parameter_kind(dtype):
    spec = parse_spec(
        {
            "states": ["x"],
            "equations": {"x": "-a*x + sum_nbr(b_j*x_j) + lin(H)"},
            "params": {"a": 1.0, "b": [1.0, 2.0], "H": [[0.0, 0.5], [0.25, 0.0]]},
        }
    )
    params = {k: v.to(dtype).requires_grad_() for k, v in spec.params.items()}
    x = torch.randn(2, 2, 1, dtype=dtype)
    out = _eval(spec, x, make_topology("complete", 2), params=params)
    assert out.dtype == dtype
    out.square().sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in params.values())


def test_nothing_in_an_expression_is_executed(tmp_path):
    marker = tmp_path / "pwned"
    payloads = [
        f"__import__('pathlib').Path('{marker}').write_text('x')",
        f"open('{marker}', 'w')",
        "(lambda: 1)()",
        "omega.real",
        "[omega][0]",
        "omega if 1 else 2",
    ]
    for text in payloads:
        with pytest.raises(ConfigError):
            _spec(equations={"theta": "omega", "omega": text})
    assert not marker.exists()


@pytest.mark.parametrize(
    "equation, message",
    [
        ("omegaa", "unknown name 'omegaa'. Did you mean 'omega'"),
        ("-(gg/l)*sin(theta)", "Did you mean 'g'"),
        ("sinn(theta)", "unknown function 'sinn'. Did you mean 'sin'"),
        ("theta_j", "only defined inside sum_nbr"),
        ("sum_nbr(sum_nbr(theta_j))", "cannot be nested"),
        ("sin(theta, omega)", "takes exactly one argument"),
        ("g_j", "only states, inputs and per-node parameters"),
        ("sin", "is a function"),
        ("omega +", "cannot parse"),
    ],
)
def test_bad_equations_get_one_clear_message(equation, message):
    with pytest.raises(ConfigError, match="model.spec.equations.omega") as err:
        _spec(equations={"theta": "omega", "omega": equation})
    assert message in str(err.value)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"equations": {"theta": "omega"}}, "no equation for ['omega']"),
        ({"equations": {"theta": "omega", "omega": "0", "phi": "1"}}, "'phi' is not a state"),
        ({"learnable": ["gg"]}, "Did you mean 'g'"),
        ({"params": {"g": [1.0, 2.0], "l": [1.0, 2.0, 3.0], "k": 1.0}}, "node counts disagree"),
        ({"params": {"g": float("nan"), "l": 1.0, "k": 1.0}}, "NaN or infinite"),
        ({"params": {"g": "fast", "l": 1.0, "k": 1.0}}, "expected a number"),
        ({"states": ["theta", "lambda"]}, "not a valid identifier"),
        ({"states": ["theta", "omega_j"]}, "ends in '_j'"),
        ({"kinematic": ["phi"]}, "not a state"),
        ({"equatons": {}}, "Did you mean 'equations'"),
    ],
)
def test_bad_specs_get_one_clear_message(changes, message):
    with pytest.raises(ConfigError) as err:
        _spec(**changes)
    assert message in str(err.value)


def test_kinematic_rows_detected_or_declared():
    assert _spec().kinematic == ("theta",)
    assert _spec(kinematic=[]).kinematic == ()
    spec = parse_spec({"states": ["x", "v"], "equations": {"x": "v", "v": "-x"}, "kinematic": ["x"]})
    assert spec.kinematic == ("x",)


def test_spec_file_reading(tmp_path):
    good = tmp_path / "s.yaml"
    good.write_text("states: [x]\nequations: {x: -a*x}\nparams: {a: 2}\n")
    assert parse_spec(load_spec_file(good)).params["a"] == 2.0
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    (tmp_path / "bad.yaml").write_text("states: [x\n")
    (tmp_path / "obj.yaml").write_text("!!python/object/apply:os.system ['true']\n")
    (tmp_path / "folder.yaml").mkdir()
    for name, message in [
        ("missing.yaml", "does not exist"),
        ("folder.yaml", "folder.yaml is a folder, not a file; give a path to a YAML file"),
        ("list.yaml", "not a mapping"),
        ("bad.yaml", "cannot read spec file"),
        ("obj.yaml", "cannot read spec file"),
    ]:
        with pytest.raises(ConfigError, match=message):
            load_spec_file(tmp_path / name)


X = sympy.Symbol("x")


@pytest.mark.parametrize(
    "eq, match",
    [
        ("x*9**9**9**9", "the constant 9**387420489 is about 10^3.7e+08, beyond float64"),  # used to hang
        ("x*2**-(10**200)", "beyond float64"),  # an exact 1/2^(1e200): as hopeless
        ("x*10**400", "is about 10^400"),
    ],
)
def test_a_power_of_constants_beyond_float64_is_refused_before_it_is_computed(eq, match):
    with pytest.raises(ConfigError, match=re.escape(match)):
        parse_spec({"states": ["x"], "equations": {"x": eq}})
    assert parse_spec({"states": ["x"], "equations": {"x": "x*10**300"}}).rhs[0] == sympy.Integer(10) ** 300 * X


@pytest.mark.parametrize("eq", ["x*1e309", "x + 1/0", "x*exp(exp(exp(exp(10))))", "x*sqrt(-1)"])
def test_a_constant_that_is_not_a_finite_real_number_is_refused_naming_its_equation(eq):
    spec = parse_spec({"states": ["x"], "equations": {"x": eq}})
    with pytest.raises(ConfigError, match=r"^model\.spec\.equations\.x: .* is not a finite real number"):
        EquationField(spec)


def test_a_spec_file_reads_exponent_notation_as_numbers(tmp_path):
    """PyYAML's YAML 1.1 reads `1e-3` as text; a spec file means what the same keys inline in a config mean."""
    path = tmp_path / "spec.yaml"
    path.write_text("states: [x]\nequations: {x: -k*x}\nparams: {k: 2e-3}\ndt: 1E2\nname: 1e\n")
    spec = load_spec_file(path)
    assert spec["params"]["k"] == 0.002 and spec["dt"] == 100.0 and spec["name"] == "1e"
    assert float(parse_spec(spec, extra_keys=["dt", "name"]).params["k"]) == 0.002


# ---- inputs (issue 60): values the data give, used like states, with no equation of their own -------------
DRIVEN = {
    "states": ["x", "v"],
    "inputs": ["u", "w"],
    "equations": {"x": "v", "v": "(k*u - Fv*v)/M + c*sum_nbr(u_j - u) + w*sin(x)"},
    "params": {"k": 2.0, "Fv": 0.3, "M": 1.5, "c": 0.5},
}


def test_inputs_are_read_like_states_and_their_neighbour_values_too():
    spec = parse_spec(DRIVEN)
    assert spec.inputs == ("u", "w") and spec.input_dim == 2 and spec.kinematic == ("x",)
    ei = make_topology("ring", 4)
    x, u = torch.randn(3, 4, 2, dtype=torch.float64), torch.randn(3, 4, 2, dtype=torch.float64)
    graph = batch_graph(ei, 3, 4, dtype=x.dtype)
    out = EquationField(spec)(torch.tensor(0.0), x, dict(spec.params), graph, u)
    uu, ww = u[..., 0], u[..., 1]
    nbr = torch.zeros_like(uu).index_add_(1, ei[1], uu[:, ei[0]]) - 2 * uu  # ring: in-degree 2
    expected = (2.0 * uu - 0.3 * x[..., 1]) / 1.5 + 0.5 * nbr + ww * torch.sin(x[..., 0])
    assert torch.allclose(out[..., 0], x[..., 1]) and torch.allclose(out[..., 1], expected, atol=1e-13)
    with pytest.raises(ConfigError, match=r"reads the inputs \['u', 'w'\].* got none"):
        EquationField(spec)(torch.tensor(0.0), x, dict(spec.params), graph)
    with pytest.raises(ConfigError, match=r"got shape \[3, 4, 1\]"):
        EquationField(spec)(torch.tensor(0.0), x, dict(spec.params), graph, u[..., :1])


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"inputs": ["u", "x"]}, "model.spec.inputs names 'x', which is also a state"),
        ({"inputs": ["u", "u"]}, "lists a name twice"),
        ({"inputs": ["u", "w_j"]}, "input name 'w_j' ends in '_j'"),
        ({"inputs": ["u", "t"]}, "input name 't' is reserved"),
        ({"inputs": "u"}, "must be a list of names"),
        ({"params": {"k": 2.0, "Fv": 0.3, "M": 1.5, "c": 0.5, "w": 1.0}}, "params.w has the name of an input"),
        ({"equations": {"x": "v", "v": "u", "u": "0"}}, "'u' is an input (its values come from the data's controls)"),
        ({"equations": {"x": "v", "v": "k*G"}}, "unknown name 'G'. Known: states ['x', 'v'], inputs ['u', 'w']"),
        ({"inputs": None, "equations": {"x": "v", "v": "k*F"}}, "declared under inputs:"),
    ],
)
def test_bad_inputs_get_one_clear_message(changes, message):
    with pytest.raises(ConfigError) as err:
        parse_spec({**DRIVEN, **changes})
    assert message in str(err.value)
