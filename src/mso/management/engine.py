"""The engine of the management rules (paper §3.5): each evaluation the node hands
:meth:`RuleEngine.evaluate` a :class:`~mso.management.views.Snapshot`; the rules propose
actions, the guard holds back those not confirmed or over a rate limit, and the engine returns
the rest and logs every decision. Pure, deterministic.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import msgspec

from mso.management.guard import Guard, Proposal, RuleSettings
from mso.management.policy import LifetimePolicy, Policy
from mso.management.rules import (
    ChainRouteRule,
    EnergyRemapRule,
    RelocationRule,
    draining_update,
    lifetime_ratio,
    warming_until,
)
from mso.management.views import Action, ActionKey, Relocate, RemapChain, RemapChains, Snapshot

LogEntry = tuple[float, str, str]


class EngineStatus(msgspec.Struct, frozen=True, kw_only=True):
    """What the rules run by and what they decided lately, for status."""

    policy: str
    app_policies: dict[str, str]  # app -> its own policy
    settings: dict[str, Any]  # RuleSettings, by field
    evaluations: int
    draining: list[str]  # this node, while its battery is draining
    warming_until: float | None
    decisions: list[str]  # "time what: decision", recent


class RuleEngine:
    """Runs the rules on a snapshot and returns the actions the guard allows.

    Every app is managed by its own policy if one was set (:meth:`set_app_policy`, from the
    app's ``policy:``), else by the node's. Per app, each evaluation collects the policy's own
    ``actions()`` (relocations need ``confirm``, remaps ``slo_confirm`` evaluations in a row)
    and the relocation rule's proposal; the route rule adds chain remaps. At most one
    relocation is returned per evaluation. While this node warms up (:func:`warming_until`)
    the relocation and energy-remap rules propose nothing and the draining state stands: the
    figures they would weigh are the start-up's, not the node's. A policy that raises is
    reported in the log and its app skipped for that evaluation. ``log`` keeps recent decisions
    as ``(now, action, "allowed" | "held: why" | "ignored: why" | "error: what")``, each
    written when it changes.
    """

    def __init__(
        self,
        policy: Policy | None = None,
        settings: RuleSettings | None = None,
        *,
        log_size: int = 200,
    ) -> None:
        self.policy = policy if policy is not None else LifetimePolicy()
        self.settings = settings if settings is not None else RuleSettings()
        self.app_policies: dict[str, Policy] = {}
        self.guard = Guard(self.settings)
        self.route_rule = ChainRouteRule(self.settings)
        self.log: deque[LogEntry] = deque(maxlen=log_size)
        self.evaluations = 0
        self.draining: frozenset[str] = frozenset()  # this node, while its battery is draining
        self.warming: float | None = None  # until when this node warms up (warming_until)
        self._last: dict[tuple[Any, ...], str] = {}
        # which rule proposed each action the last evaluation allowed (a move says who asked)
        self.rule_of: dict[ActionKey, str] = {}

    def set_app_policy(self, app: str, policy: Policy | None) -> None:
        """Manage ``app`` by ``policy`` (None: by the node's policy again)."""
        if policy is None:
            self.app_policies.pop(app, None)
        else:
            self.app_policies[app] = policy

    def policy_for(self, app: str) -> Policy:
        return self.app_policies.get(app, self.policy)

    def forget(self, app: str) -> None:
        """Drop what the engine keeps about an app that stopped."""
        self.app_policies.pop(app, None)
        self.route_rule.forget(app)

    def evaluate(self, snap: Snapshot) -> list[Action]:
        self.evaluations += 1
        self.rule_of = {}
        seen: dict[tuple[Any, ...], str] = {}
        proposals = self.route_rule.propose(snap)
        was = self.draining
        self.draining = draining_update(was, snap, self.settings)
        if self.draining != was:
            ratio = lifetime_ratio(snap, snap.here)
            shown = "-" if ratio is None else f"{ratio:.2f}"
            what = "draining" if snap.here in self.draining else "no longer draining"
            self.log.append((snap.now, f"{snap.here} {what}", f"lifetime ratio {shown}"))
        warm = self.warming is None
        self.warming = warming_until(snap, self.settings)
        if warm and self.warming is not None:
            self.log.append(
                (
                    snap.now,
                    f"{snap.here} warming up",
                    f"a vertex started {snap.now - (snap.last_start or snap.now):.1f} s ago: "
                    f"its drain is judged {self.warming - snap.now:.1f} s from now",
                )
            )
        for app in snap.apps():
            policy = self.policy_for(app)
            view = snap.for_app(app)
            try:
                asked = list(policy.actions(view))
                relocations: list[Proposal] = []
                energy: list[Proposal] = []
                if self.warming is None:  # start-up in the figures: no move for energy or load
                    relocations = RelocationRule(policy, self.settings, self.draining).propose(view)
                    energy = EnergyRemapRule(policy, self.settings, self.draining).propose(view)
            except Exception as exc:  # user code: report it, keep the node running
                what = f"policy {policy.name} for {app}"
                self._note(
                    seen, ("error", app), snap.now, what, f"error: {type(exc).__name__}: {exc}"
                )
                continue
            for act in asked:
                proposal, problem = self._check(act, view, policy)
                if proposal is None:
                    decision = f"ignored: {problem}"
                    self._note(seen, ("ignored", repr(act)), snap.now, str(act), decision)
                else:
                    proposals.append(proposal)
            proposals.extend(relocations)
            proposals.extend(energy)
        allowed: list[Action] = []
        for p, why in self.guard.review(proposals, snap):
            a = p.action
            if why is None:
                allowed.append(a)
                self.rule_of[a.key] = p.rule
                indices: tuple[int, ...] = (a.chain,) if isinstance(a, RemapChain) else ()
                indices = a.chains if isinstance(a, RemapChains) else indices
                for index in indices:
                    chain = snap.chain(a.app, index)
                    if chain is not None:
                        self.route_rule.done(chain)
            self._note(seen, a.key, snap.now, str(a), "allowed" if why is None else f"held: {why}")
        self._last = seen
        return allowed

    def _check(self, act: object, snap: Snapshot, policy: Policy) -> tuple[Proposal | None, str]:
        """A policy's own action as a proposal, or why it cannot be one."""
        rule = f"policy {policy.name}"
        if isinstance(act, Relocate):
            v = snap.vertex(act.vertex_key)
            if v is None:
                return None, f"{act.vertex_key} is not hosted on {snap.here}"
            if not v.movable:
                return None, f"{v.key} is a chain end or pinned: never relocated"
            if act.target == v.node:
                return None, f"{v.key} already runs on {v.node}"
            if act.target not in snap.nodes:
                return None, f"no view of node {act.target}"
            return Proposal(act, self.settings.confirm, 0.0, rule), ""
        if isinstance(act, RemapChain):
            chain = snap.chain(act.app, act.chain)
            if chain is None or not chain.coordinator:
                return None, f"{snap.here} does not coordinate {act.app} chain {act.chain}"
            return Proposal(act, self.settings.slo_confirm, 0.0, rule), ""
        return None, f"not an action: {act!r}"

    def _note(
        self,
        seen: dict[tuple[Any, ...], str],
        key: tuple[Any, ...],
        now: float,
        what: str,
        decision: str,
    ) -> None:
        seen[key] = decision
        if self._last.get(key) != decision:
            self.log.append((now, what, decision))

    def status(self) -> EngineStatus:
        """Policies, settings and recent decisions, for ``mso status``."""
        s = self.settings
        return EngineStatus(
            policy=self.policy.name,
            app_policies={a: p.name for a, p in sorted(self.app_policies.items())},
            settings={name: getattr(s, name) for name in s.__dataclass_fields__},
            evaluations=self.evaluations,
            draining=sorted(self.draining),
            warming_until=self.warming,
            decisions=[f"{t:.1f} {what}: {d}" for t, what, d in self.log],
        )
