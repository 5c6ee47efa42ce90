"""mesh.security: who may speak in a run (docs/security.md).

    credentials   the per-run CA, one certificate and key per process identity, zenoh's access control
    access        the access rules as the simulated network enforces them

May import: core, estimators, data, engine, mesh.wire.
"""
