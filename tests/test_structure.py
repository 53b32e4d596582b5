"""The structure the code keeps (issue 59), checked from the source with `ast` (nothing is imported but the API):

- only `prepare` (the composition root, `mpsim.commands.prepare`) and the `run_<command>` wrappers read a config
  object: below them every function takes plain values. The config layer itself is left out: `mpsim/config`
  (the schemas and the checks of a composed config, which build nothing), `mpsim/cli.py` (dispatch, before a run
  starts) and the two Hydra callbacks, which Hydra hands its own config (`mpsim/runfolder.py`: the run folder
  before it is made; `mpsim/commands/sweep_end.py`: the table at the end of a sweep);
- no function is over 80 lines and no source file over 500;
- the public API imports, and each of its names has a docstring with an example.

Run as a script to print the figures: `python tests/test_structure.py` (who reads a config, the longest function,
the largest file, the public names with their docstring examples, and each docs/ page's size against
tests/test_docs.py's limit and allow-list).
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


def function_sizes() -> list[tuple[int, str]]:
    """(lines, `file:function`) of every function, longest first."""
    sizes = []
    for path in _sources():
        for fn in _functions(path):
            sizes.append(((fn.end_lineno or fn.lineno) - fn.lineno + 1, f"{path.relative_to(SRC)}:{fn.name}"))
    return sorted(sizes, reverse=True)


def file_sizes() -> list[tuple[int, str]]:
    """(lines, file) of every source file, largest first."""
    return sorted(((len(p.read_text().splitlines()), str(p.relative_to(SRC))) for p in _sources()), reverse=True)


def long_functions() -> list[tuple[int, str]]:
    return [s for s in function_sizes() if s[0] > MAX_FUNCTION_LINES]


def long_files() -> list[tuple[int, str]]:
    return [s for s in file_sizes() if s[0] > MAX_FILE_LINES]


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


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_the_script_prints_its_figures(capsys):
    assert main() == 0
    out = capsys.readouterr().out
    assert "longest function:" in out and "largest file:" in out and "docs pages:" in out


def _print_public_api() -> None:
    import mpsim

    print(f"public API (mpsim.__all__): {len(PUBLIC)} names")
    for name in PUBLIC:
        obj = getattr(mpsim, name)
        examples = sum(line.strip().startswith(">>>") for line in (obj.__doc__ or "").splitlines())
        print(f"  {name:13s} imports from {obj.__module__:26s} docstring example lines: {examples}")


def _print_docs_pages() -> None:
    from test_docs import MAX_PAGE_BYTES, OVERSIZED_PAGES  # the page rules live with their test

    pages = sorted((SRC.parents[1] / "docs").glob("*.md"))
    over = [p.name for p in pages if p.stat().st_size > MAX_PAGE_BYTES]
    print(
        f"docs pages: {len(pages)}, over {MAX_PAGE_BYTES // 1024} KB: {len(over)} (allow-listed in test_docs.py: "
        f"{', '.join(sorted(OVERSIZED_PAGES))})"
    )
    for page in pages:
        kb = page.stat().st_size / 1024
        note = "" if page.name not in over else "  OVER (allow-listed)" if page.name in OVERSIZED_PAGES else "  OVER"
        print(f"  {kb:5.1f} KB  {page.name}{note}")


def main() -> int:
    readers = config_readers()
    print(f"functions that take a config object: {len(readers)}")
    for r in readers:
        print(f"  {r}")
    functions, files = function_sizes(), file_sizes()
    print(
        f"longest function: {functions[0][1]}, {functions[0][0]} lines (limit {MAX_FUNCTION_LINES}; "
        f"over it: {len(long_functions())} of {len(functions)})"
    )
    print(
        f"largest file: {files[0][1]}, {files[0][0]} lines (limit {MAX_FILE_LINES}; "
        f"over it: {len(long_files())} of {len(files)})"
    )
    for n, name in long_functions() + long_files():
        print(f"  over: {n:4d} {name}")
    _print_public_api()
    _print_docs_pages()
    return 0


if __name__ == "__main__":
    sys.exit(main())
