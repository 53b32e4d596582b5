"""Which run folders a report reads (`mpsim.report.runs`)."""

import json
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


def test_a_free_run_gives_a_column_per_record_and_channel_averaged_over_seeds(tmp_path):
    from mpsim.report.plain import plain_table
    from mpsim.report.runs import collect

    for seed, rmse in ((0, 0.2), (1, 0.4)):
        run = tmp_path / f"r{seed}"
        (run / ".hydra").mkdir(parents=True)
        (run / ".hydra" / "overrides.yaml").write_text(f"- seed={seed}\n")
        free = {"records": [{"record": "/d/unif_1.csv", "channels": {"y": {"rmse": rmse, "fit": 50.0 + seed}}}]}
        (run / "summary.json").write_text(json.dumps({"task": "train", "test_error": 1.0, "freerun": free}))
    frame = collect([tmp_path])
    assert sorted(frame["freerun_unif_1_y_rmse"]) == [0.2, 0.4]
    table = plain_table(frame, [], [])
    assert len(table) == 1 and table["freerun_unif_1_y_rmse"].iloc[0].startswith("0.3")  # mean ± std, not a group
