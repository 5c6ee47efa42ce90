"""diskf-mesh: decentralized input and state estimation (DISKF) on a
peer-to-peer mesh of agent processes.

Layout of the estimation core:
    equations   the paper's equations, pure batched numpy functions
    rkf         the Gillijns & De Moor RKF measurement update (baselines)
    algorithms  DISKF and the baselines, each a local step + a fuse step
    model       motion model, sensors, estimator parameters
    scenario    TOML scenarios and their simulation
    trace       recorded data and its JSON formats
    engine      the in-process engine (all agents and seeds at once)
    metrics     MAE, RMSE, input coverage, NEES
"""
__version__ = "0.1.0"
