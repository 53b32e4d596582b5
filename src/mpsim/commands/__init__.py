"""Command layer: one `run_<command>(cfg) -> dict` per `mpsim` command; the only code that reads configs."""
