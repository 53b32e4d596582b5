"""The structure the code keeps (issue 59), checked from the source with `ast` (nothing is imported but the API):

- only `prepare` (the composition root, `mpsim.commands.prepare`) and the `run_<command>` wrappers read a config
  object: below them every function takes plain values. The config layer itself is left out: `mpsim/config`
  (the schemas and the checks of a composed config, which build nothing), `mpsim/cli.py` (dispatch, before a run
  starts) and the two Hydra callbacks, which Hydra hands its own config (`mpsim/runfolder.py`: the run folder
  before it is made; `mpsim/commands/sweep_end.py`: the table at the end of a sweep);
- no function is over 80 lines and no source file over 500;
- the public API imports, and each of its names has a docstring with an example.

Run as a script to print the figures: `python tests/test_structure.py`.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "mpsim"
CONFIG_LAYER = ("config.py", "config/", "cli.py", "resume.py", "runfolder.py", "commands/sweep_end.py")
MAX_FUNCTION_LINES = 80
MAX_FILE_LINES = 500
PUBLIC = ("System", "Trajectories", "Model", "Trainer", "simulate", "rollout")


def _sources() -> list[Path]:
    return sorted(SRC.rglob("*.py"))


def _functions(path: Path) -> list[ast.FunctionDef | ast.AsyncFunctionDef]:
    tree = ast.parse(path.read_text())
    return [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]


def _reads_config(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """A parameter named `cfg` or annotated as an omegaconf `DictConfig`."""
    args = [*fn.args.posonlyargs, *fn.args.args, *fn.args.kwonlyargs]
    for arg in args:
        note = ast.unparse(arg.annotation) if arg.annotation is not None else ""
        if arg.arg == "cfg" or "DictConfig" in note:
            return True
    return False


def config_readers() -> list[str]:
    """`file:function` of every function below the config layer that takes a config object."""
    found = []
    for path in _sources():
        if path.relative_to(SRC).as_posix().startswith(CONFIG_LAYER):
            continue
        for fn in _functions(path):
            if _reads_config(fn):
                found.append(f"{path.relative_to(SRC)}:{fn.name}")
    return found


def long_functions() -> list[tuple[int, str]]:
    out = []
    for path in _sources():
        for fn in _functions(path):
            lines = (fn.end_lineno or fn.lineno) - fn.lineno + 1
            if lines > MAX_FUNCTION_LINES:
                out.append((lines, f"{path.relative_to(SRC)}:{fn.name}"))
    return sorted(out, reverse=True)


def long_files() -> list[tuple[int, str]]:
    sizes = [(len(p.read_text().splitlines()), str(p.relative_to(SRC))) for p in _sources()]
    return sorted((n, p) for n, p in sizes if n > MAX_FILE_LINES)


def test_only_prepare_and_the_run_wrappers_read_the_config():
    readers = [r for r in config_readers() if not r.endswith((":prepare",)) and ":run_" not in r]
    assert not readers, f"functions below the run_<command> wrappers that take a config object: {readers}"


def test_run_wrappers_live_in_commands():
    stray = [r for r in config_readers() if ":run_" in r and not r.startswith("commands/")]
    assert not stray, f"run_<command> wrappers outside mpsim/commands/: {stray}"


def test_no_function_is_over_80_lines():
    assert not long_functions(), f"functions over {MAX_FUNCTION_LINES} lines: {long_functions()}"


def test_no_source_file_is_over_500_lines():
    assert not long_files(), f"source files over {MAX_FILE_LINES} lines: {long_files()}"


@pytest.mark.parametrize("name", PUBLIC)
def test_public_api_imports_with_an_example(name):
    import mpsim

    obj = getattr(mpsim, name)
    doc = obj.__doc__ or ""
    assert ">>>" in doc or "Example" in doc, f"mpsim.{name} has no example in its docstring"
    assert name in mpsim.__all__


def main() -> int:
    readers = config_readers()
    print(f"functions that take a config object: {len(readers)}")
    for r in readers:
        print(f"  {r}")
    print(f"functions over {MAX_FUNCTION_LINES} lines: {len(long_functions())}")
    for n, name in long_functions():
        print(f"  {n:4d} {name}")
    print(f"source files over {MAX_FILE_LINES} lines: {len(long_files())}")
    for n, name in long_files():
        print(f"  {n:4d} {name}")
    n_files = len(_sources())
    n_funcs = sum(len(_functions(p)) for p in _sources())
    print(f"(checked {n_files} files, {n_funcs} functions under {SRC.relative_to(SRC.parents[1])})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
