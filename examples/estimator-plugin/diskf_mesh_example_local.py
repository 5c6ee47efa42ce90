"""``example-local``: each agent's local Kalman filter, no fusion.

A complete diskf-mesh estimator in one module (docs/estimators.md). It
predicts, updates with the agent's own measurement (the information-form
update every estimator shares, ``Estimator.local_kf``) and reports that;
what it hears from its neighbours is ignored. It still sends the standard
message, so it runs unchanged in the engine and on the mesh. Its one
parameter shows how a setting is declared: ``report_input`` (the
scenario's ``[estimator] report_input``, the CLI's ``--report-input``).
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.messages import Output
from diskf_mesh.estimators.base import Estimator, Setting, State

REPORT_INPUT = Setting("report_input", True, "example-local: report the agent's own input estimate "
                       "(off: no input estimate at all)")


class ExampleLocal(Estimator):
    name = "example-local"
    label = "Local KF"
    color = "tab:gray"
    settings = (REPORT_INPUT,)

    def local(self, state, k, y, has):
        loc = self.local_kf(state, k, y, has)            # prediction and the agent's own update
        d, S, valid = self.local_input(loc)              # its own input estimate (sent, as every estimator does)
        return State(loc.x_upd, loc.P_upd, state.since), self.message(loc, d, S, valid)

    def fuse(self, state, own, senders, nb):
        valid = own.d_valid if self.params.report_input else np.zeros_like(own.d_valid)
        return state, Output(state.x, state.P, own.d, valid)
