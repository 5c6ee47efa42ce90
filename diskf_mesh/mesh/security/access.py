"""A run's access rules as the simulated network enforces them.

``Access(policy)`` reads zenoh's ``access_control`` document of a run
(``credentials.access_control``: default deny, one subject per certificate
common name, rules by message kind, flow and key expression) and answers
``allowed(identity, message, key, flow)`` the way zenoh applies it to a
peer's traffic: a put travels from P to Q only if P may put it (ingress at
Q, by P's certificate) and Q may receive it (egress to Q, by Q's); a
subscription, a token, a watch, a query or a queryable only if its
declarer's rules allow that message on that expression. ``Access(None)``
(a run without credentials) allows everything.

An identity that is no subject of the policy (no certificate of the run)
may do nothing. The expressions that allow one (identity, message, flow)
are gathered once (each compiled as a matcher when a key is not one of
them; ``keys.matcher`` keeps it); answers are remembered per
(identity, message, key, flow), ``MEMO`` of them (a run's puts repeat
their keys every tick: every pair of linked agents' is one).

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

from diskf_mesh.mesh.wire.keys import matcher

MEMO = 1 << 21


class Access:
    def __init__(self, policy: dict | None):
        self.enabled = bool(policy and policy.get("enabled", True))
        self._rules = {}  # identity -> [(flows, messages, key expressions)] allowed
        self._grants = {}  # (identity, message, flow) -> (the expressions allowing it, their matchers)
        self._memo = {}
        if not self.enabled:
            return
        if policy.get("default_permission", "deny") != "deny":
            raise ValueError("only a default-deny policy is modelled")
        rules = {r["id"]: r for r in policy.get("rules", ())}
        names = {s["id"]: tuple(s.get("cert_common_names", ())) for s in policy.get("subjects", ())}
        for pol in policy.get("policies", ()):
            granted = [rules[r] for r in pol["rules"] if rules[r].get("permission") == "allow"]
            for subject in pol["subjects"]:
                for cn in names.get(subject, ()):
                    self._rules.setdefault(cn, []).extend(
                        (frozenset(r["flows"]), frozenset(r["messages"]), tuple(r["key_exprs"])) for r in granted)

    def allowed(self, identity: str | None, message: str, key: str, flow: str = "ingress") -> bool:
        if not self.enabled:
            return True
        memo = (identity, message, key, flow)
        hit = self._memo.get(memo)
        if hit is not None:
            return hit
        # a rule covers a key, or an expression its own wildcards match chunk for chunk (or itself)
        exprs = self._exprs(identity, message, flow)
        hit = key in exprs or any(matcher(e)(key) is not None for e in exprs)
        if len(self._memo) >= MEMO:
            self._memo.clear()
        self._memo[memo] = hit
        return hit

    def _exprs(self, identity: str | None, message: str, flow: str) -> frozenset:
        """The key expressions that allow ``identity`` ``message`` on ``flow``
        (their matchers are compiled when a key is not one of them)."""
        grant = self._grants.get((identity, message, flow))
        if grant is None:
            grant = self._grants[(identity, message, flow)] = frozenset(
                e for flows, messages, es in self._rules.get(identity, ()) if flow in flows and message in messages
                for e in es)
        return grant

    def put(self, sender: str | None, receiver: str | None, key: str, via: str | None = None) -> bool:
        """A put of ``sender`` on ``key`` reaches ``receiver``; ``via``: an
        expression ``key`` is known to match (the receiver's subscription
        that matched it), which allows it at once where one of the
        receiver's rules is that expression."""
        if not self.allowed(sender, "put", key):
            return False
        if via is not None and self.enabled and via in self._exprs(receiver, "put", "egress"):
            return True
        return self.allowed(receiver, "put", key, "egress")
