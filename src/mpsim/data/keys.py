"""The names in `data.columns`, `data.observed` and `data.control_columns` checked against the model's own, before a
file is read: a key the model does not have (a typo, `Q` for `q`) is refused with the valid names and a close match,
never ignored (the file's column of the right name would be read instead, unseen).

Torch-free: `mpsim.cli` runs it before Hydra makes a run folder, on the names a spec states; `mpsim.data.pipeline`
runs it again with the names of the model actually built (a checkpoint's).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from mpsim.errors import ConfigError, did_you_mean


def check_data_names(
    columns: Mapping[str, str] | None,
    observed: Sequence[str],
    controls: Sequence[str],
    states: Sequence[str] | None,
    inputs: Sequence[str] | None,
    outputs: Sequence[str] = (),
) -> None:
    """Refuse names the model does not have.

    Args:
        columns: `data.columns`, {model name: file column}.
        observed: `data.observed`, the states the file holds.
        controls: `data.control_columns`, the model's inputs read from the file.
        states, inputs: the model's states and inputs when it states them (a spec); None: it takes the data's.
        outputs: the spec's outputs (what its sensors read): measured names too.
    """
    observed, controls = list(observed), list(controls)
    if states is not None:
        states = [s for s in states if s not in outputs]
        kind = "state or output" if outputs else "state"
        _each_in("data.observed", observed, [*states, *outputs], kind, states, inputs, outputs=outputs)
    if inputs is not None and states is not None:
        _each_in("data.control_columns", controls, list(inputs), "input", states, inputs)
    keys = [str(k) for k in (columns or {})]
    if states is not None:
        known = [*states, *(inputs or []), *outputs]
        kind = "state, input or output" if outputs else "state or input"
        _each_in("data.columns", keys, known, kind, states, inputs, mapping=True, outputs=outputs)
        left_out = [k for k in keys if observed and k in [*states, *outputs] and k not in observed]
        if left_out:
            k = left_out[0]
            raise ConfigError(
                f"data.columns maps '{k}' to column '{(columns or {})[k]}', but data.observed={observed} leaves "
                f"'{k}' out, so that column would not be read ('{k}' would be estimated). Add '{k}' to "
                "data.observed to use the column, or drop it from data.columns."
            )
    elif observed:
        known = [*observed, *controls]
        unknown = [k for k in keys if k not in known]
        if unknown:
            k = unknown[0]
            raise ConfigError(
                f"data.columns maps '{k}', which is neither in data.observed={observed} nor in "
                f"data.control_columns={controls}, so it would not be read.{did_you_mean(k, known)} List it there, "
                "or drop it from data.columns."
            )


def _each_in(
    key: str,
    names: list[str],
    known: list[str],
    kind: str,
    states: Sequence[str],
    inputs: Sequence[str] | None,
    mapping: bool = False,
    outputs: Sequence[str] = (),
) -> None:
    unknown = [n for n in names if n not in known]
    if not unknown:
        return
    n = unknown[0]
    has = f"its states: {', '.join(states)}" + (f"; its inputs: {', '.join(inputs)}" if inputs else "; no inputs")
    has += f"; its outputs: {', '.join(outputs)}" if outputs else ""
    given = "{" + ", ".join(f"{k}: ..." for k in names) + "}" if mapping else f"[{', '.join(names)}]"
    raise ConfigError(
        f"{key}={given}: '{n}' is not a{'n' if kind[0] in 'aeiou' else ''} {kind} of the model ({has})."
        f"{did_you_mean(n, known)} Use the model's names; map them to the file's columns with "
        "data.columns={<name>: <column>}."
    )
