"""The public API: what `mpsim` exports, its docstring examples, and docs/python.md's snippets run."""

import doctest
import re
import subprocess
import sys
from pathlib import Path

import pytest

import mpsim

PUBLIC = ["System", "Trajectories", "Model", "Trainer", "simulate", "rollout"]
PYTHON_PAGE = Path(__file__).resolve().parents[1] / "docs" / "python.md"


def test_mpsim_exports_exactly_the_public_names():
    assert mpsim.__all__ == [*PUBLIC, "__version__"]
    homes = {name: getattr(mpsim, name).__module__ for name in PUBLIC}
    assert homes == {
        "System": "mpsim.systems.base",
        "Trajectories": "mpsim.data.trajectories",
        "Model": "mpsim.models.base",
        "Trainer": "mpsim.training.trainer",
        "simulate": "mpsim.systems.simulation",
        "rollout": "mpsim.models.rollout",
    }
    with pytest.raises(AttributeError, match="has no attribute 'predict'"):
        mpsim.predict  # noqa: B018


@pytest.mark.parametrize("name", PUBLIC)
def test_each_public_name_has_an_example_that_runs(name, tmp_path, monkeypatch):
    obj = getattr(mpsim, name)
    assert "Examples:" in (obj.__doc__ or ""), f"mpsim.{name}'s docstring has no Examples: section"
    monkeypatch.chdir(tmp_path)  # whatever an example writes stays here
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    for test in doctest.DocTestFinder(recurse=False).find(obj, f"mpsim.{name}", globs={}):
        runner.run(test)
    failed, attempted = runner.summarize(verbose=False)
    assert attempted >= 3 and failed == 0, f"mpsim.{name}: {failed} of {attempted} example lines failed (see stdout)"


@pytest.mark.slow  # 3–6 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_importing_mpsim_or_its_cli_does_not_import_torch_until_a_public_name_is_used():
    probe = (
        "import sys\n"
        "import mpsim, mpsim.cli\n"
        "assert 'torch' not in sys.modules, 'import mpsim.cli imported torch'\n"
        "from mpsim import rollout, Trainer\n"
        "assert 'torch' in sys.modules and rollout.__module__ == 'mpsim.models.rollout'\n"
    )
    subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True)


def test_the_python_page_runs(tmp_path, monkeypatch):
    """docs/python.md's ```python blocks, in order, as one script (in a scratch folder: it trains into run/)."""
    blocks = re.findall(r"^```python\n(.*?)^```", PYTHON_PAGE.read_text(), re.S | re.M)
    assert len(blocks) >= 5
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "python_md"}
    for block in blocks:
        exec(compile(block, str(PYTHON_PAGE), "exec"), namespace)
    assert (tmp_path / "run" / "metrics.csv").is_file()
    assert len(PYTHON_PAGE.read_bytes()) <= 6 * 1024
