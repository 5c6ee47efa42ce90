"""studies: the paper's experiments and the report built from them.

    experiment  settings x estimators x seeds on the engine, and the table
    suite       the report's studies (Table II, range sweep, ablations, robustness)
    figures     the figures (matplotlib, imported only when drawing)
    report      docs/reproduction.md and results.json

May import: core, estimators, data, engine.
"""
