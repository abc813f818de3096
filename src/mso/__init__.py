"""mso: Mobile Service Overlays.

Run a dataflow application across the devices of a mobile ad hoc network and keep re-placing it
as batteries drain, nodes move and routes change. The public API::

    from mso import App, load_app, form_chains, plan, load_scenario
"""

from mso.errors import AppError, MsoError, PlanningError, ScenarioError, SpecError
from mso.model.app import App, Edge, Vertex
from mso.model.appfile import load_app, loads_app
from mso.model.chains import Chain, chain_order, form_chains
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.planning.placement import Hop, Plan, place_chain, plan
from mso.scenario import Scenario, load_scenario, loads_scenario

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
