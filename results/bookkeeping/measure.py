"""Per-epoch bookkeeping of a long run, side by side in one process: the two layouts of `last.ckpt`'s history
and the two ways of writing `metrics.csv`.

A trainer rewrites `last.ckpt` (with every metric row so far, for an exact resume) and `metrics.csv` after
every epoch. Before 2026-11-27 the history was a list of dicts, which the content checksum hashed value by
value, and the CSV was formatted again in full; both grew with the epoch count. Now the rows are one JSON text
(`history_text`) and each CSV row is formatted once. Usage, from the repository root:

    python results/bookkeeping/measure.py <a last.ckpt of a long run> [repeats]

Prints a markdown table: seconds per epoch for each, median of `repeats`.
"""

import csv
import io
import statistics
import sys
import tempfile
import time
from pathlib import Path

from mpsim.files import atomic_write
from mpsim.training.checkpoint import history_row, history_text, load_checkpoint, save_checkpoint
from mpsim.training.loggers import CSVLogger


def median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main(path: str, repeats: int = 9) -> None:
    payload = load_checkpoint(path)  # either layout: the rows come back as `history`
    rows = payload["trainer"].pop("history")
    columns = list(rows[0])
    texts = [history_row(r, columns) for r in rows]
    trainer = {k: v for k, v in payload["trainer"].items() if k not in ("history", "history_json")}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)

        def ckpt_list() -> None:  # before: the rows as a list of dicts
            save_checkpoint(out / "a.ckpt", {**payload, "trainer": {**trainer, "history": rows}})

        def ckpt_text() -> None:  # now: the rows as one text (each row dumped once, as the trainer does)
            save_checkpoint(
                out / "b.ckpt", {**payload, "trainer": {**trainer, "history_json": history_text(columns, texts)}}
            )

        def csv_full() -> None:  # before: every row formatted again
            buf = io.StringIO()
            writer = csv.DictWriter(buf, fieldnames=columns)
            writer.writeheader()
            writer.writerows(rows)
            atomic_write(out / "a.csv", lambda f: f.write(buf.getvalue()), mode="w")

        logger = CSVLogger("b.csv")
        logger.start(out, {}, rows[:-1])

        def csv_kept() -> None:  # now: the earlier rows' text kept, one row formatted
            logger.lines.pop()  # the same last row again each repeat
            logger.log_epoch(rows[-1])

        logger.log_epoch(rows[-1])
        csv_full()
        same_csv = (out / "a.csv").read_bytes() == (out / "b.csv").read_bytes()
        results = {
            name: median_time(fn, repeats)
            for name, fn in [
                ("ckpt_list", ckpt_list),
                ("ckpt_text", ckpt_text),
                ("csv_full", csv_full),
                ("csv_kept", csv_kept),
            ]
        }
        sizes = {n: (out / n).stat().st_size for n in ("a.ckpt", "b.ckpt")}
    r = results
    print(f"History of {len(rows)} epochs ({path}); median of {repeats}; metrics.csv identical: {same_csv}\n")
    print("| per epoch | before | now | before / now |\n|---|---|---|---|")
    print(
        f"| last.ckpt save (s) | {r['ckpt_list']:.4f} | {r['ckpt_text']:.4f} | {r['ckpt_list'] / r['ckpt_text']:.1f}× |"
    )
    print(
        f"| metrics.csv write (s) | {r['csv_full']:.4f} | {r['csv_kept']:.4f} | {r['csv_full'] / r['csv_kept']:.1f}× |"
    )
    before, now = r["ckpt_list"] + r["csv_full"], r["ckpt_text"] + r["csv_kept"]
    print(f"| both (s) | {before:.4f} | {now:.4f} | {before / now:.1f}× |")
    print(f"| last.ckpt size (MB) | {sizes['a.ckpt'] / 1e6:.2f} | {sizes['b.ckpt'] / 1e6:.2f} | |")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 9)
