"""The import structure of `src/mpsim`: no cycle, no upward import, no private name used across modules.

Every module under `src/mpsim` is read with `ast` (never imported). Every `import` counts: at module level,
deferred inside a function, and under `if TYPE_CHECKING:` (a type-only import still couples the two modules: the
one that is imported cannot later import the other without a cycle that a type checker, and any reader, sees).
An import of a package's submodule (`from mpsim.models import mpnode`) is an edge to the submodule; an import of
a name from a package (`from mpsim.models import MPNODE`) is an edge to the package's `__init__`. The implicit
import of a parent package when a submodule is imported is not an edge (every submodule would otherwise depend
on its package's re-exports).

Layers, lowest first; a module may import only modules of its own layer or of a lower one (within one layer the
graph must still be acyclic):

    0  base       errors, files, memory, conf, version, process   plain helpers: messages, atomic files, memory,
                                                                   the version, the entry points' process set-up
    1  numerics   periodic, polynomials, metrics, effects,        the maths: periodic geometry, monomials, losses
                  equations, graphs, solvers, estimate            and metrics, effects, topologies, integrators,
                                                                   state estimators over a caller's step function
    2  data       data                                           trajectories, file IO, splits, cache
    3  systems    systems                                        ground-truth simulators (they make `Trajectories`)
    4  models     models                                         learnable simulators, `rollout`
    5  analysis   diagnose, plotting                             the residual loop (it predicts with `rollout` and
                                                                   finetunes through a callback), plots
    6  training   training                                       the trainer, checkpoints, loggers, DDP
    7  bench      bench                                          benchmarks (one of DDP training)
    8  config     config                                         config -> objects; keys and run records
    9  report     report                                         reports of finished runs (plain values, no cfg)
   10  commands   commands                                       `run_<cmd>(cfg) -> dict`
   11  entry      cli, resume, __main__, mpsim (the facade)      command dispatch, resume=, process set-up

A command (one of `COMMANDS`) never imports another command: what two commands share lives in a helper module of
`mpsim.commands` (`runtime`, `building`, `console`, ...) or in a library module below; a helper never imports a command.

A private name (`_x`, not a dunder) defined in one module is never imported or used (`module._x`) from another;
a private module (`_x.py`) may be imported only from inside its own package.

The scripts under `results/` (records of how a result was made) import the library (`mpsim.report`, ...), never
`mpsim.commands`: a command's helpers may change without notice, a library function keeps its name.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path

import pytest

from mpsim.process import configure_process

SRC = Path(__file__).resolve().parents[1] / "src"
RESULTS = Path(__file__).resolve().parents[1] / "results"
ROOT = "mpsim"

LAYERS: list[tuple[str, list[str]]] = [
    (
        "base",
        [
            "mpsim.errors",
            "mpsim.files",
            "mpsim.memory",
            "mpsim.conf",
            "mpsim.version",
            "mpsim.process",
            "mpsim.safeload",
            "mpsim.runfolder",
            "mpsim.console",
        ],
    ),
    (
        "numerics",
        [
            "mpsim.periodic",
            "mpsim.polynomials",
            "mpsim.signals",
            "mpsim.metrics",
            "mpsim.effects",
            "mpsim.spec",
            "mpsim.graphs",
            "mpsim.solvers",
            "mpsim.estimate",
        ],
    ),
    ("data", ["mpsim.data"]),
    ("systems", ["mpsim.systems"]),
    ("models", ["mpsim.models"]),
    ("analysis", ["mpsim.diagnose", "mpsim.plotting"]),
    ("training", ["mpsim.training"]),
    ("bench", ["mpsim.bench"]),
    ("config", ["mpsim.config"]),
    ("report", ["mpsim.report"]),
    ("commands", ["mpsim.commands"]),
    ("entry", ["mpsim.cli", "mpsim.resume", "mpsim.help", "mpsim.__main__", "mpsim"]),
]
# The command modules (`mpsim <command>`); every other module of `mpsim.commands` is a helper.
COMMANDS = {f"mpsim.commands.{c}" for c in ("train", "eval", "simulate", "diagnose", "report", "bench")}


@dataclass
class Module:
    """One source module: its dotted name, whether it is a package `__init__`, and what it imports."""

    name: str
    is_package: bool
    rel: str  # path under the source root, for messages
    tree: ast.Module
    edges: dict[str, int] = field(default_factory=dict)  # imported mpsim module -> first line
    private_uses: list[tuple[int, str, str]] = field(default_factory=list)  # (line, module, private name)


def module_name(path: Path, src: Path = SRC) -> tuple[str, bool]:
    """Dotted module name of a file under `src`, and whether it is a package `__init__`."""
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "__init__":
        return ".".join(parts[:-1]), True
    return ".".join(parts), False


def load_modules(src: Path = SRC, root: str = ROOT) -> dict[str, Module]:
    """Every module of package `root` under `src`, parsed."""
    mods = {}
    for path in sorted((src / root).rglob("*.py")):
        name, is_package = module_name(path, src)
        mods[name] = Module(name, is_package, str(path.relative_to(src)), ast.parse(path.read_text(), str(path)))
    return mods


def resolve_from(mod: Module, node: ast.ImportFrom) -> str:
    """The absolute module of a `from ... import` (relative levels resolved against `mod`)."""
    if not node.level:
        return node.module or ""
    base = mod.name.split(".")
    if not mod.is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def owner(name: str, mods: dict[str, Module]) -> str | None:
    """The longest known module that `name` (a dotted path) starts with, or None outside the package."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        candidate = ".".join(parts[:k])
        if candidate in mods:
            return candidate
    return None


def scan(mods: dict[str, Module]) -> None:
    """Fill each module's import edges and its uses of other modules' private names."""
    for mod in mods.values():
        aliases: dict[str, str] = {}  # local name -> dotted mpsim path it is bound to (a module, or a name in one)
        for node in ast.walk(mod.tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    target = owner(a.name, mods)
                    if target is None:
                        continue
                    mod.edges.setdefault(target, node.lineno)
                    check_private_module(mod, target, node.lineno)
                    head = a.name.split(".")[0]
                    aliases[a.asname or head] = target if a.asname else head
            elif isinstance(node, ast.ImportFrom):
                base = resolve_from(mod, node)
                target = owner(base, mods)
                if target is None:
                    continue
                for a in node.names:
                    full = f"{base}.{a.name}"
                    aliases[a.asname or a.name] = full
                    if full in mods:  # a submodule
                        mod.edges.setdefault(full, node.lineno)
                        check_private_module(mod, full, node.lineno)
                        continue
                    mod.edges.setdefault(target, node.lineno)
                    check_private_module(mod, target, node.lineno)
                    if is_private(a.name):
                        mod.private_uses.append((node.lineno, target, a.name))
        for node in ast.walk(mod.tree):
            if isinstance(node, ast.Attribute) and is_private(node.attr):
                dotted = dotted_name(node.value)
                if dotted is None:
                    continue
                head, _, rest = dotted.partition(".")
                if head not in aliases:
                    continue
                target = owner(".".join(filter(None, [aliases[head], rest])), mods)
                if target is not None and target != mod.name:
                    mod.private_uses.append((node.lineno, target, node.attr))
        mod.edges.pop(mod.name, None)


def check_private_module(mod: Module, target: str, line: int) -> None:
    """Record an import of a private module (`pkg._x`) from outside the package `pkg`."""
    parts = target.split(".")
    for i in range(1, len(parts)):
        package = ".".join(parts[:i])
        if is_private(parts[i]) and not (mod.name == package or mod.name.startswith(package + ".")):
            mod.private_uses.append((line, package, parts[i]))


def package_of(mod: Module) -> str:
    """The package a module belongs to (a package `__init__` belongs to itself)."""
    return mod.name if mod.is_package else mod.name.rsplit(".", 1)[0]


def is_private(name: str) -> bool:
    """`_x` but not `__x__`."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def dotted_name(node: ast.expr) -> str | None:
    """`a.b.c` for a chain of names and attributes, else None."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([node.id, *reversed(parts)])


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the directed graph as `[a, b, ..., a]`, or None when it is acyclic."""
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for start in sorted(edges):
        if start not in state:
            found = visit(start)
            if found:
                return found
    return None


def layer_of(name: str, layers: list[tuple[str, list[str]]] = LAYERS) -> int:
    """Index of the layer whose longest prefix matches the module `name` (the root package `mpsim` matches only
    itself, so that a new module must be given a layer)."""
    best, best_len = -1, -1
    for i, (_, prefixes) in enumerate(layers):
        for p in prefixes:
            if (name == p or (p != ROOT and name.startswith(p + "."))) and len(p) > best_len:
                best, best_len = i, len(p)
    if best < 0:
        raise AssertionError(f"module {name} is in no layer: add it to LAYERS in {__file__}")
    return best


def upward_imports(mods: dict[str, Module], layers: list[tuple[str, list[str]]] = LAYERS) -> list[str]:
    """Every import from a lower layer to a higher one, and every command that imports another command."""
    bad = []
    for mod in mods.values():
        low = layer_of(mod.name, layers)
        for target, line in sorted(mod.edges.items()):
            high = layer_of(target, layers)
            if high > low:
                bad.append(f"{mod.rel}:{line} {mod.name} ({layers[low][0]}) imports {target} ({layers[high][0]})")
            elif target in COMMANDS and mod.name.startswith("mpsim.commands"):
                kind = "command" if mod.name in COMMANDS else "command helper"
                bad.append(f"{mod.rel}:{line} {kind} {mod.name} imports command {target}")
    return bad


def graph(mods: dict[str, Module]) -> dict[str, set[str]]:
    return {m.name: set(m.edges) for m in mods.values()}


@pytest.fixture(scope="module")
def modules() -> dict[str, Module]:
    mods = load_modules()
    scan(mods)
    return mods


def test_no_import_cycle(modules):
    cycle = find_cycle(graph(modules))
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_no_upward_import(modules):
    bad = upward_imports(modules)
    assert not bad, "imports against the layer order (see tests/test_imports.py):\n" + "\n".join(bad)


def test_no_private_name_across_modules(modules):
    bad = [f"{m.rel}:{line} uses {target}.{name}" for m in modules.values() for line, target, name in m.private_uses]
    assert not bad, "private names used outside their module:\n" + "\n".join(sorted(bad))


def write_package(tmp_path: Path, files: dict[str, str]) -> dict[str, Module]:
    for rel, text in files.items():
        path = tmp_path / ROOT / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    mods = load_modules(tmp_path)
    scan(mods)
    return mods


def test_checker_finds_a_cycle_held_by_deferred_and_type_checking_imports(tmp_path):
    mods = write_package(
        tmp_path,
        {
            "__init__.py": "",
            "solvers/__init__.py": "",
            "solvers/a.py": "def f():\n    from mpsim.solvers.b import g\n    return g\n",
            "solvers/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import c\n",
            "solvers/c.py": "import mpsim.solvers.a as a\n",
            "solvers/d.py": "from mpsim.solvers import a\n",
        },
    )
    cycle = find_cycle(graph(mods))
    assert cycle == ["mpsim.solvers.a", "mpsim.solvers.b", "mpsim.solvers.c", "mpsim.solvers.a"]
    assert find_cycle({"x": {"y"}, "y": {"z"}, "z": set()}) is None


def test_checker_finds_upward_and_command_to_command_imports(tmp_path):
    mods = write_package(
        tmp_path,
        {
            "__init__.py": "",
            "models/__init__.py": "",
            "models/m.py": "from mpsim.training.metrics import rmse\n",
            "training/__init__.py": "",
            "training/metrics.py": "from mpsim.models import m\n",
            "commands/__init__.py": "",
            "commands/common.py": "from mpsim.commands import eval\n",
            "commands/train.py": "from mpsim.commands.common import x\nfrom mpsim.commands.eval import y\n",
            "commands/eval.py": "from mpsim.training import metrics\n",
        },
    )
    bad = upward_imports(mods)
    assert len(bad) == 3, bad
    assert any("mpsim.models.m (models) imports mpsim.training.metrics (training)" in b for b in bad)
    assert any("command mpsim.commands.train imports command mpsim.commands.eval" in b for b in bad)
    assert any("command helper mpsim.commands.common imports command mpsim.commands.eval" in b for b in bad)


def test_checker_finds_private_names_used_across_modules(tmp_path):
    mods = write_package(
        tmp_path,
        {
            "__init__.py": "",
            "plotting.py": "def _save(): pass\n",
            "diagnose/__init__.py": "",
            "diagnose/_solve.py": "",
            "diagnose/select.py": "def _lstsq(): pass\nfrom . import _solve\n",
            "diagnose/loop.py": "from mpsim.diagnose import select\nselect._lstsq()\n",
            "commands/__init__.py": "",
            "commands/x.py": (
                "import mpsim.plotting\nfrom mpsim.diagnose.select import _lstsq\n"
                "from mpsim.diagnose import _solve\nmpsim.plotting._save()\n"
            ),
            "commands/y.py": (
                "import mpsim.diagnose._solve as s\nfrom mpsim.plotting import Figure\nFigure._canvas\n"
                "def f(fig):\n    return fig._private_but_untracked\n"
            ),
        },
    )
    found = sorted((m.name, target, name) for m in mods.values() for _, target, name in m.private_uses)
    assert found == [
        ("mpsim.commands.x", "mpsim.diagnose", "_solve"),
        ("mpsim.commands.x", "mpsim.diagnose.select", "_lstsq"),
        ("mpsim.commands.x", "mpsim.plotting", "_save"),
        ("mpsim.commands.y", "mpsim.diagnose", "_solve"),
        ("mpsim.commands.y", "mpsim.plotting", "_canvas"),
        ("mpsim.diagnose.loop", "mpsim.diagnose.select", "_lstsq"),
    ]


def command_imports(root: Path) -> list[str]:
    """Every import of `mpsim.commands` (or of a module in it) in the Python files under `root`, as
    "path:line module"."""
    bad = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or "", *(f"{node.module}.{a.name}" for a in node.names)]
            else:
                continue
            if any(n == "mpsim.commands" or n.startswith("mpsim.commands.") for n in names):
                bad.append(f"{path.relative_to(root)}:{node.lineno} {names[0]}")
    return bad


def test_results_scripts_import_no_command():
    bad = command_imports(RESULTS)
    assert not bad, "scripts under results/ import the command layer (import mpsim.report instead):\n" + "\n".join(bad)


def test_checker_finds_a_results_script_that_imports_a_command(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "old.py").write_text("from mpsim.commands.report_layouts import min_so_far\n")
    (tmp_path / "b.py").write_text("import os\nfrom mpsim import commands\nimport mpsim.commands.report as r\n")
    (tmp_path / "ok.py").write_text("from mpsim.report import min_so_far\nimport mpsim.commands_like\n")
    assert command_imports(tmp_path) == [
        "a/old.py:1 mpsim.commands.report_layouts",
        "b.py:2 mpsim",
        "b.py:3 mpsim.commands.report",
    ]


IMPORT_PROBE = """
import json, os, sys
import matplotlib
matplotlib.use("svg")  # the caller's own choice, which importing mpsim must keep
env = dict(os.environ)
import mpsim, mpsim.cli, mpsim.plotting, mpsim.report, mpsim.commands.report, mpsim.commands.train
mpsim.Trajectories, mpsim.System
changed = sorted(k for k in set(env) | set(os.environ) if env.get(k) != os.environ.get(k))
print(json.dumps({"changed": changed, "backend": matplotlib.get_backend(), "version": mpsim.__version__}))
"""


@pytest.mark.slow  # 3–6 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_import_has_no_process_wide_side_effects():
    """`import mpsim` (and its plotting and command modules) sets no environment variable and keeps the caller's
    matplotlib backend; only the entry point (`mpsim.process.configure_process`) sets the process up."""
    env = {k: v for k, v in os.environ.items() if k not in ("THP_MEM_ALLOC_ENABLE", "MPLBACKEND")}
    out = subprocess.run([sys.executable, "-c", IMPORT_PROBE], env=env, capture_output=True, text=True, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result == {"changed": [], "backend": "svg", "version": version("mpsim")}


def test_entry_point_sets_the_process_up(monkeypatch):
    monkeypatch.delenv("THP_MEM_ALLOC_ENABLE", raising=False)
    monkeypatch.setenv("MPSIM_KEEP_HEAP", "0")  # leave this test process's allocator alone
    assert configure_process() is False
    assert os.environ["THP_MEM_ALLOC_ENABLE"] == "1"
