"""Which run folders a report reads (`mpsim.report.runs`)."""

import shutil

from mpsim.report import collect, unfinished
from tests.report.fake_runs import fake_run


def test_an_earlier_run_moved_to_a_backup_is_not_a_run_of_its_own(tmp_path):
    # overwrite=true moves the earlier run into <run>/backup-<time>/ (mpsim.runfolder): reported, it counted twice
    run = fake_run(tmp_path / "runs", "a", system="lorenz3", errors=[1.0, 0.5, 0.4])
    earlier = fake_run(tmp_path / "old", "a", system="lorenz3", errors=[1.0, 0.9, 0.8])
    shutil.move(earlier, run / "backup-20261206-120000")
    interrupted = fake_run(tmp_path / "old", "b", system="lorenz3", errors=[1.0, 0.9])
    (interrupted / "summary.json").unlink()  # an earlier run that never finished: not "unfinished" here either
    shutil.move(interrupted, run / "backup-20261206-130000")
    assert collect([tmp_path / "runs"])["run"].tolist() == [str(run)]
    assert unfinished([tmp_path / "runs"]) == []
    backup = run / "backup-20261206-130000"
    assert [r["run"] for r in unfinished([backup])] == [str(backup)]  # named itself, it is reported
