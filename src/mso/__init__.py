"""mso: Mobile Service Overlays.

Run a dataflow application across the devices of a mobile ad hoc network and keep re-placing it
as batteries drain, nodes move and routes change. The public API::

    from mso import App, load_app, form_chains, plan, load_scenario
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mso.errors import AppError, MsoError, PlanningError, ScenarioError, SpecError
    from mso.model.app import App, Edge, Vertex
    from mso.model.appfile import load_app, loads_app
    from mso.model.chains import Chain, chain_order, form_chains
    from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
    from mso.planning.placement import Hop, Plan, place_chain, plan
    from mso.scenario import Scenario, load_scenario, loads_scenario

# imported when first used (PEP 562), so `mso status` does not pay for numpy and the planner
_WHERE = {
    "AppError": "mso.errors", "MsoError": "mso.errors", "PlanningError": "mso.errors",
    "ScenarioError": "mso.errors", "SpecError": "mso.errors",
    "App": "mso.model.app", "Edge": "mso.model.app", "Vertex": "mso.model.app",
    "load_app": "mso.model.appfile", "loads_app": "mso.model.appfile",
    "Chain": "mso.model.chains", "chain_order": "mso.model.chains",
    "form_chains": "mso.model.chains",
    "LinkSpec": "mso.model.network", "Network": "mso.model.network",
    "NodeSpec": "mso.model.network", "PowerModel": "mso.model.network",
    "Hop": "mso.planning.placement", "Plan": "mso.planning.placement",
    "place_chain": "mso.planning.placement", "plan": "mso.planning.placement",
    "Scenario": "mso.scenario", "load_scenario": "mso.scenario",
    "loads_scenario": "mso.scenario",
}  # fmt: skip


def __getattr__(name: str) -> Any:
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'mso' has no attribute {name!r}")
    value = getattr(importlib.import_module(where), name)
    globals()[name] = value
    return value


__all__ = [
    "App",
    "AppError",
    "Chain",
    "Edge",
    "Hop",
    "LinkSpec",
    "MsoError",
    "Network",
    "NodeSpec",
    "Plan",
    "PlanningError",
    "PowerModel",
    "Scenario",
    "ScenarioError",
    "SpecError",
    "Vertex",
    "chain_order",
    "form_chains",
    "load_app",
    "load_scenario",
    "loads_app",
    "loads_scenario",
    "place_chain",
    "plan",
]
