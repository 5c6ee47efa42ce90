"""The numbers the paper prints (Wu and Mehta, arXiv:2410.00272: its
Table I and Table II), for comparison.

Only the two tables carry numbers; Figs. 3, 5 and 6 are plots without
values in the source. Keys follow ``metrics.METRIC_KEYS`` and the estimator
names of ``estimators.NAMES``; ``COLUMNS`` are the paper's six, in its order.
"""
from __future__ import annotations

COLUMNS = ("diskf", "cdrkf", "ldrkf", "kcf", "diffkf", "gdkf")


def _rows(**rows) -> dict:
    return {metric: dict(zip(COLUMNS, values)) for metric, values in rows.items()}


# Table II: four static agents (Scenario 1), {topology: {metric: {estimator: value}}}
TABLE_II = {
    "all": _rows(mae_state=(1.91, 1.91, 15.66, 27.90, 27.90, 36.20),
                 rmse_state=(2.66, 2.66, 25.05, 40.45, 40.45, 50.15),
                 mae_input=(4.63, 4.63, 6.87, 15.39, 15.39, 14.01),
                 rmse_input=(6.35, 6.35, 9.75, 16.51, 16.51, 15.12)),
    "ring": _rows(mae_state=(15.76, 26.76, 26.08, 37.40, 24.87, 40.92),
                  rmse_state=(30.05, 55.63, 41.54, 53.41, 40.84, 58.89),
                  mae_input=(4.67, 9.73, 6.30, 15.11, 14.53, 13.35),
                  rmse_input=(6.37, 17.34, 9.72, 16.94, 15.47, 14.33)),
    "none": _rows(mae_state=(63.75, 71.01, 71.01, 66.43, 66.43, 65.82),
                  rmse_state=(92.88, 109.31, 109.31, 90.78, 90.78, 90.36),
                  mae_input=(9.10, 21.76, 21.76, 16.32, 16.32, 12.65),
                  rmse_input=(12.21, 32.33, 32.33, 17.95, 17.95, 14.50)),
}

# Table I: DISKF with ("yes") and without ("no") state compensation,
# {(environment, communication): {"yes"|"no": {metric: value}}}, as printed.
# Note: the stationary 1-hop "yes" row has input and state swapped with
# respect to Table II (15.76/30.05 are state there, 4.67/6.37 input).
_T1_COLS = ("mae_input", "rmse_input", "mae_state", "rmse_state")
TABLE_I = {
    (env, comm): {flag: dict(zip(_T1_COLS, vals)) for flag, vals in rows.items()}
    for (env, comm), rows in {
        ("stationary", "all-to-all"): {"yes": (4.63, 6.35, 1.91, 2.66), "no": (4.63, 6.35, 1.91, 2.66)},
        ("stationary", "1-hop"): {"yes": (15.76, 30.05, 4.67, 6.37), "no": (26.75, 55.63, 7.38, 15.36)},
        ("dynamic", "all-to-all"): {"yes": (1.56, 4.01, 7.40, 11.08), "no": (1.56, 4.01, 7.40, 11.08)},
        ("dynamic", "1-hop"): {"yes": (10.37, 19.34, 8.82, 14.22), "no": (16.14, 26.47, 9.11, 14.76)},
    }.items()
}
