"""Tools that work on a trained run folder: `dyngs-eval`, `dyngs-render`, `dyngs-export`,
and `dyngs-bench`, which trains and compares a sweep of configs.

Each is a tyro CLI over a frozen config dataclass (`EvalConfig`, …) with a `run_*`
function that does the work, so they can be called from Python as well. Run folders are
loaded by `dyngs.runs.load_run`.
"""
