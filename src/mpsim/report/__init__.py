"""Reports of finished runs: the library under `mpsim report` (which only reads its config and calls this).

A report reads only what every run records (summary.json, metrics.csv, .hydra/config.yaml and overrides.yaml),
so it works on any mix of run and sweep directories: runs are sorted into rows and columns by what they are (model
class, mode, system, training-set size, message size), never by where they lie.

- `runs`: collect the runs under some folders (`collect`), name those that began training but wrote no
  summary.json (`unfinished`, `unfinished_note`).
- `plain`: the plain table, one row per group of runs that differ only by seed, metrics as mean ± std.
- `layouts`: the built-in tables and figures of the MP-NODE paper by name, and the report each writes
  (`layout_report`); one module per layout: `table2` (Table 2), `table1` (Table 1), `curves` (Figure 5),
  `message_size` (Figures 7 and 8), `messages` (Figures 3a and 4). Each takes the frame of runs that
  `mark_variants` returns (its `variant` column) and returns Markdown, a long-format table (→ CSV) and writes its
  PNG figures.
- `variants`: runs that share a layout's place (system, model class, mode, training-set size, message size, ...)
  are averaged as seeds only when they were run with the same settings: where their resolved configs
  (`.hydra/config.yaml`, the model's config as summary.json records it) differ in anything but seeds, places on
  disk, hardware or what is written out, `mark_variants` keeps them apart, and every layout's row says how they
  differ, e.g. "MP-NODE (model.self_loops=true)".
- `common`: what the layouts share (names, statistics over seeds, Markdown tables, learning curves).
- `paper`: the paper's published numbers, read from the data file `published/mpnode_paper.yaml`.

Nothing here reads a config object or imports `mpsim.commands`: functions take plain values.
"""

from mpsim.report.common import LayoutResult, md_table, min_so_far, pm, read_metrics
from mpsim.report.layouts import DEFAULT_TITLES, LAYOUT_FUNCS, layout_report
from mpsim.report.plain import add_epochs_to_target, aggregate, jobs_table, plain_table, plain_text
from mpsim.report.runs import (
    collect,
    read_overrides,
    read_summary,
    run_facts,
    run_settings,
    shown,
    unfinished,
    unfinished_note,
)
from mpsim.report.variants import mark_variants, settings_caption

__all__ = [
    "DEFAULT_TITLES",
    "LAYOUT_FUNCS",
    "LayoutResult",
    "add_epochs_to_target",
    "aggregate",
    "collect",
    "layout_report",
    "mark_variants",
    "md_table",
    "min_so_far",
    "plain_table",
    "plain_text",
    "jobs_table",
    "pm",
    "read_metrics",
    "read_overrides",
    "read_summary",
    "run_facts",
    "run_settings",
    "settings_caption",
    "shown",
    "unfinished",
    "unfinished_note",
]
