"""`layout=messages` (`mpsim.report.messages`): Figures 3a and 4, MP-NODE with messages vs `zero_messages=true`."""

import pandas as pd

from tests.report.fake_runs import fake_run, report_of


def test_messages_layout_compares_messages_on_and_off(tmp_path):
    root = tmp_path / "runs"
    for seed in (0, 1):  # train loss is 10× the error (see _run)
        errors = [3, 1, 0.8, 0.5, 0.2 + 0.1 * seed]
        fake_run(root, f"on{seed}", system="pendulum2", seed=seed, zero_messages=False, errors=errors)
    fake_run(root, "off", system="pendulum2", zero_messages=True, errors=[3, 1, 0.9, 0.9, 0.9])
    fake_run(root, "old", system="pendulum2", seed=2, errors=[3, 1, 0.6, 0.4, 0.3])  # no flag recorded: messages on
    fake_run(
        root, "l2s", system="pendulum2", model="L2S", message_size=None, errors=[3, 0.1, 0.1, 0.1, 0.1]
    )  # not MP-NODE
    fake_run(
        root, "zs", system="pendulum2", zero_messages=False, trained_on="pendulum2", best_val=0.1
    )  # trains nothing
    _, out = report_of(tmp_path, "messages", root)
    text = (out / "report.md").read_text()
    assert "| on | 3 | 2.67 ± 0.58 | 0.267 ± 0.058 | 1.067 ± 0.23 |" in text  # 0.2, 0.3 and the old run's 0.3
    assert "| off (`zero_messages=true`) | 1 | 9 | 0.9 | 1.8 |" in text
    assert "Messages off / on: train loss 3.38×, test error 3.38× — messages lower both" in text
    assert "| messages | by epoch 1 | by epoch 2 | by epoch 3 | by epoch 4 |" in text
    assert "| on | 10 ± 0 | 7.33 ± 1.2 | 4.67 ± 0.58 | 2.67 ± 0.58 |" in text
    assert "| off (`zero_messages=true`) | 10 | 9 | 9 | 9 |" in text
    table = pd.read_csv(out / "report.csv")
    assert list(table["messages"]) == ["on", "off"] and list(table["runs"]) == [3, 1]
    assert (out / "messages.png").is_file()


def test_messages_layout_says_when_messages_do_not_help(tmp_path):
    root = tmp_path / "runs"
    fake_run(root, "on", system="kuramoto10_ba", zero_messages=False, errors=[3, 1, 0.9])
    fake_run(root, "off", system="kuramoto10_ba", zero_messages=True, errors=[3, 1, 0.5])
    _, out = report_of(tmp_path, "messages", root)
    assert "test error 0.556× — messages do NOT lower both" in (out / "report.md").read_text()
