"""data: what goes into a run and what comes out of it, as files and numbers.

    scenario      TOML scenarios, their validation and their simulation
    validate      typed checks of user values (one-line errors naming the field)
    trace         recorded data and its JSON formats (diskf-trace/1, estimates)
    schemas/      the JSON Schemas of those formats
    faults        the seeded fault model (loss, latency, duplicates, delay)
    metrics       MAE, RMSE, input coverage, NEES
    paper_values  the paper's published numbers, for comparison
    outputs       output paths checked before work, atomic writes

May import: core, estimators.
"""
