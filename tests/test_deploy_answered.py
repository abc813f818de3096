"""Every deployment is answered, accepted or refused with its reason, before the client stops
waiting: a node held failed for a moment when the deployment arrives, the origin's own reset,
an undeploy meanwhile, a second request for the same app (in virtual time)."""

from __future__ import annotations

import itertools

import msgspec
import pytest

from mso.client import waiting
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.protocol.effects import Reply
from mso.protocol.procedures.base import REPLY_MARGIN_S
from mso.protocol.procedures.deploy import PINNED_WAIT_S, Deploy, _deadline_s
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app
from test_faults import held_failed_both_ways

# the fresh-clone flake's app: src pinned to N1, sink pinned to N4, nothing between
PAIR_APP = (
    pipe_app(200)
    .replace("  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num}\n", "")
    .replace("  - [src, mid]\n  - [mid, sink]\n", "  - [src, sink]\n")
)


def line(n: int, delay_ms: float = 0.1) -> Network:
    ids = [f"N{i}" for i in range(1, n + 1)]
    links = [LinkSpec(a, b, delay_ms=delay_ms) for a, b in itertools.pairwise(ids)]
    return Network([NodeSpec(i) for i in ids], links)


def n4_held_failed() -> Simulation:
    """N1 and N4 linked; N4's daemon is down (its machine routes on) and N1 holds it failed,
    as a daemon not started yet is held by a peer configured to reach it."""
    sim = Simulation(
        Network([NodeSpec("N1"), NodeSpec("N4")], [LinkSpec("N1", "N4", delay_ms=0.1)])
    )
    sim.run_until(1.0)
    sim.crash("N4")
    sim.run_until(3.0)
    assert sim.cores["N1"].failed == {"N4"} and "N4" in sim.cores["N1"].routes
    return sim


def deploy_replies(sim: Simulation, client: int = 1) -> list[tuple[float, m.DeployReply]]:
    return [(at, r) for at, c, r in sim.replies if c == client and isinstance(r, m.DeployReply)]


@pytest.mark.parametrize("gap_s", [0.002, 0.2, 1.0])
def test_a_node_back_moments_after_it_was_declared_failed_takes_part(gap_s: float) -> None:
    """The deployment arrives while N1 holds N4, the sink's pinned node, failed; N4 rejoins
    ``gap_s`` later. It was announced at once, skipping N4, so N4 never took the app and
    the deployment ran out its 30 s (past the client's wait, in a daemon); now it waits for
    N4 and succeeds."""
    sim = n4_held_failed()
    t0 = sim.now
    sim.request("N1", m.DeployRequest(PAIR_APP, "pipe.yaml"))
    sim.run_until(t0 + gap_s)
    sim.revive("N4")
    sim.run_until(t0 + gap_s + 1.0)
    ((_, reply),) = deploy_replies(sim)
    assert reply.ok, reply.error
    assert reply.placement == {"src": "N1", "sink": "N4"}
    assert "sink" in sim.cores["N4"].instances("pipe")
    assert sim.cores["N1"].open_procedures(sim.now) == []


def test_a_pinned_node_that_stays_failed_is_named_in_the_refusal() -> None:
    sim = n4_held_failed()
    t0 = sim.now
    sim.request("N1", m.DeployRequest(PAIR_APP, "pipe.yaml"))
    sim.run_until(t0 + PINNED_WAIT_S - 0.1)
    assert deploy_replies(sim) == []  # waiting for N4
    sim.run_until(t0 + PINNED_WAIT_S + 0.1)
    ((_, reply),) = deploy_replies(sim)
    assert not reply.ok
    assert "vertex 'sink' is pinned to node 'N4', held failed" in reply.error
    assert sim.cores["N1"].open_procedures(sim.now) == []
    assert "pipe" not in sim.cores["N1"].apps  # never announced


def test_the_refusal_comes_before_the_client_stops_waiting() -> None:
    """The client says how long it waits (``within_s``): the deadline falls before."""
    sim = n4_held_failed()
    t0 = sim.now
    sim.request("N1", m.DeployRequest(PAIR_APP, "pipe.yaml", within_s=3.0))
    sim.run_until(t0 + 3.0)
    ((at, reply),) = deploy_replies(sim)
    assert at == pytest.approx(t0 + 3.0 - REPLY_MARGIN_S)
    assert not reply.ok and "pinned to node 'N4', held failed" in reply.error


def test_the_deadline_follows_the_clients_wait() -> None:
    def deadline(within_s: float) -> float:
        return _deadline_s(m.DeployRequest("", within_s=within_s))

    assert deadline(0.0) == deadline(float("nan")) == deadline(-1.0) == Deploy.DEADLINE_S
    assert deadline(float("inf")) == deadline(1e9) == Deploy.DEADLINE_S
    assert deadline(10.0) == 10.0 - REPLY_MARGIN_S
    assert deadline(0.4) == 0.2  # a short wait: half of it


def test_a_client_says_how_long_it_waits_for_a_deployment() -> None:
    assert waiting(m.DeployRequest("doc"), 12.0) == m.DeployRequest("doc", within_s=12.0)
    assert waiting(m.DeployRequest("doc", within_s=5.0), 12.0).within_s == 5.0  # its own
    assert waiting(m.StatusRequest(), 12.0) == m.StatusRequest()


def test_a_second_request_for_an_app_being_deployed_is_refused_and_the_first_answered() -> None:
    sim = n4_held_failed()
    t0 = sim.now
    sim.request("N1", m.DeployRequest(PAIR_APP, "pipe.yaml"), client=1)
    sim.request("N1", m.DeployRequest(PAIR_APP, "pipe.yaml"), client=2)
    ((_, second),) = deploy_replies(sim, client=2)
    assert not second.ok and second.error == "an app named 'pipe' is being deployed"
    sim.revive("N4")
    sim.run_until(t0 + 1.0)
    ((_, first),) = deploy_replies(sim, client=1)
    assert first.ok, first.error


def test_an_undeploy_during_the_deployment_answers_it() -> None:
    """Slow links: the app is announced, its chains not built yet, when it is undeployed."""
    sim = Simulation(line(4, delay_ms=50.0))
    sim.run_until(1.0)
    sim.request("N1", m.DeployRequest(pipe_app(50), "pipe.yaml"), client=1)
    sim.run_until(sim.now + 0.01)
    sim.request("N1", m.StopApp("pipe"), client=2)
    ((_, reply),) = deploy_replies(sim)
    assert not reply.ok and reply.error == "N1: undeployed before the deployment finished"
    assert sim.cores["N1"].open_procedures(sim.now) == []


def test_an_origin_that_resets_answers_its_deployment() -> None:
    """N4 coordinates a deployment (waiting for N1, which it holds failed) when a healed
    partition's tie-break makes it reset: the deployment goes with its state, and the client
    is told why rather than left waiting."""
    sim = held_failed_both_ways()
    n1, n4, now = sim.cores["N1"], sim.cores["N4"], sim.now
    other = pipe_app(50).replace("name: pipe", "name: other")  # src pinned to N1
    assert not [e for e in n4.request(9, m.DeployRequest(other, "other.yaml"), now)
                if isinstance(e, Reply)]  # fmt: skip
    beat1 = msgspec.structs.replace(n1.membership.beat(), failed={"N4": 0})
    effects = n4.receive("N1", beat1, now)
    assert n4.incarnation == 1  # it yielded
    (reply,) = [e.msg for e in effects if isinstance(e, Reply) and e.client == 9]
    assert isinstance(reply, m.DeployReply) and not reply.ok
    assert reply.error == "N4: declared failed by N1, reset during the deployment"
    assert n4.open_procedures(now) == []
