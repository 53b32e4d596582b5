"""Config schemas and checks, used only by the command layer.

Before Hydra starts a run, `compose_command` composes the command line exactly as the run will (no torch
import, no run directory), turns Hydra's composition errors into one line with a did-you-mean (Hydra's own
advice, "To append to your config use +key", is the wrong fix for a typo) and checks value ranges
(`validate_values`). Two layers of checking make a typo or a wrong type fail at start with a clear message:

1. Typed structured-config schemas (`schemas`: dataclasses registered in Hydra's ConfigStore and named first in
   each primary config's defaults list) cover the fixed-shape parts: data, trainer, mode, paths, eval and the
   top-level keys. Hydra rejects unknown keys and unconvertible values while composing.
2. Nodes with a `_target_` (system, model, solver, ...) differ per target, so they are checked against the
   target's own signature (`targets.check_targets`): unknown keys get a did-you-mean, values are checked against
   the parameter annotations. A user who points a group at their own class gets the same checks for free.

The package: `schemas` (the typed sections), `keys` (what an override's key says about a run), `records` (a run's
saved overrides and its folder's name), `targets` and `values` (the checks), `compose` (the command line composed
before Hydra starts) and `suggest` (the did-you-mean for an unknown key). Every module is torch-free.
"""

from mpsim.config.compose import MAX_SWEEP_CHECKS as MAX_SWEEP_CHECKS
from mpsim.config.compose import compose_command as compose_command
from mpsim.config.compose import validate_search as validate_search
from mpsim.config.keys import host_only as host_only
from mpsim.config.keys import output_only as output_only
from mpsim.config.keys import override_key as override_key
from mpsim.config.keys import split_override as split_override
from mpsim.config.keys import stopping_rule as stopping_rule
from mpsim.config.records import file_stem as file_stem
from mpsim.config.records import read_overrides_file as read_overrides_file
from mpsim.config.records import run_name as run_name
from mpsim.config.schemas import BenchConf as BenchConf
from mpsim.config.schemas import CommonConf as CommonConf
from mpsim.config.schemas import DataConf as DataConf
from mpsim.config.schemas import DiagnoseConf as DiagnoseConf
from mpsim.config.schemas import EvalCmdConf as EvalCmdConf
from mpsim.config.schemas import EvalConf as EvalConf
from mpsim.config.schemas import ModeConf as ModeConf
from mpsim.config.schemas import PathsConf as PathsConf
from mpsim.config.schemas import ReportConf as ReportConf
from mpsim.config.schemas import SimulateConf as SimulateConf
from mpsim.config.schemas import TrainConf as TrainConf
from mpsim.config.schemas import TrainerConf as TrainerConf
from mpsim.config.schemas import register_schemas as register_schemas
from mpsim.config.targets import check_target_node as check_target_node
from mpsim.config.targets import check_targets as check_targets
from mpsim.config.targets import plain_dict as plain_dict
from mpsim.config.values import validate_values as validate_values
