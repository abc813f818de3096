"""Scenario files and the network they describe: nodes, links, routes."""

from __future__ import annotations

import itertools
import textwrap
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mso.errors import ScenarioError, SpecError
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.scenario import (
    Heal,
    LinkChange,
    LossChange,
    NodeFailure,
    NodeRestart,
    Partition,
    load_scenario,
    loads_scenario,
)

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"
FILE = "net.yaml"


def yml(text: str) -> str:
    return textwrap.dedent(text).lstrip("\n")


def scenario_error(text: str) -> SpecError:
    with pytest.raises(SpecError) as info:
        loads_scenario(yml(text), file=FILE)
    err = info.value
    assert "\n" not in str(err), "an error is one line"
    return err


def assert_at(err: SpecError, line: int | None, field: str | None, phrase: str) -> None:
    assert isinstance(err, ScenarioError), repr(err)
    assert (err.file, err.line, err.field) == (FILE, line, field), str(err)
    assert phrase in err.message, str(err)
    where = f"{FILE}:{line}: " if line else f"{FILE}: "
    assert str(err) == where + (f"{field}: " if field else "") + err.message


def network(ids: list[str], links: list[tuple[str, str]]) -> Network:
    return Network([NodeSpec(i) for i in ids], [LinkSpec(a, b) for a, b in links])


LINE4 = """
name: line4
nodes:
  N1: {}
  N2: {cpu: 2.0, battery_wh: 20}
  N3: {}
  N4: {power: {idle_w: 1.5, cpu_w: 6}}
links:
  - [N1, N2]
  - {between: [N2, N3], bandwidth_mbps: 54, delay_ms: 0.5, loss: 0.01}
  - [N3, N4]
"""


# -- loading --------------------------------------------------------------------------------


def test_line4_with_links() -> None:
    sc = loads_scenario(yml(LINE4), file=FILE)
    net = sc.network
    assert sc.name == "line4" and sc.file == FILE and sc.radio_range is None
    assert list(net.nodes) == ["N1", "N2", "N3", "N4"]
    assert net.nodes["N1"] == NodeSpec("N1")
    assert net.nodes["N2"].cpu == 2.0 and net.nodes["N2"].battery_wh == 20.0
    assert net.nodes["N4"].power == PowerModel(idle_w=1.5, cpu_w=6.0)
    assert set(net.links) == {("N1", "N2"), ("N2", "N3"), ("N3", "N4")}
    assert net.link("N3", "N2") == LinkSpec("N2", "N3", 54.0, 0.5, 0.01)
    assert net.link("N1", "N2") == LinkSpec("N1", "N2")
    assert net.link("N1", "N3") is None
    assert net.route("N1", "N4") == ["N1", "N2", "N3", "N4"]
    assert net.route("N4", "N1") == ["N4", "N3", "N2", "N1"]
    assert net.hops("N1", "N4") == 3 and net.hops("N2", "N2") == 0
    assert net.next_hop("N1", "N4") == "N2" and net.next_hop("N4", "N1") == "N3"
    assert net.next_hop("N3", "N3") == "N3"
    assert net.distances("N2") == {"N2": 0, "N1": 1, "N3": 1, "N4": 2}
    assert net.neighbours("N2") == ["N1", "N3"]


def test_example_line4_file_and_default_name(tmp_path: Path) -> None:
    sc = load_scenario(EXAMPLES / "line4.yaml")
    assert sc.name == "line4" and sc.file == str(EXAMPLES / "line4.yaml")
    assert sc.network.route("N1", "N4") == ["N1", "N2", "N3", "N4"]
    path = tmp_path / "my-net.yaml"
    path.write_text("nodes:\n  A: {}\n", encoding="utf-8")
    assert load_scenario(path).name == "my-net"
    assert loads_scenario("nodes:\n  A: {}\n").name == "scenario"


def test_radio_range_derives_links() -> None:
    sc = loads_scenario(
        yml(
            """
            radio_range: 120
            link_defaults: {bandwidth_mbps: 11, delay_ms: 2}
            nodes:
              R1: {pos: [0, 0]}
              R2: {pos: [100, 0]}
              R3: {pos: [200, 0]}
              R4: {pos: [100, 100]}
              R5: {pos: [320, 0]}
            """
        ),
        file=FILE,
    )
    net = sc.network
    assert sc.radio_range == 120.0
    assert net.nodes["R4"].pos == (100.0, 100.0)
    # Exactly at range (R3-R5, 120 m) is linked; R1-R4 (141 m) is not.
    assert set(net.links) == {("R1", "R2"), ("R2", "R3"), ("R2", "R4"), ("R3", "R5")}
    assert all(
        (lk.bandwidth_mbps, lk.delay_ms, lk.loss) == (11.0, 2.0, 0.0) for lk in net.links.values()
    )
    assert net.route("R1", "R5") == ["R1", "R2", "R3", "R5"]
    assert sc.link_template is not None and sc.link_template.delay_ms == 2.0


def test_node_and_link_defaults() -> None:
    sc = loads_scenario(
        yml(
            """
            node_defaults:
              cpu: 2
              battery_wh: 5
              power: {idle_w: 3}
            link_defaults: {delay_ms: 2, loss: 0.1}
            nodes:
              N1: {cpu: 3}
              N2: {battery_wh: null}
              N3: {power: {cpu_w: 9, idle_w: 0.5}}
            links:
              - [N1, N2]
              - {between: [N2, N3], loss: 0}
            """
        ),
        file=FILE,
    )
    n = sc.network.nodes
    assert (n["N1"].cpu, n["N1"].battery_wh, n["N1"].power.idle_w) == (3.0, 5.0, 3.0)
    assert (n["N2"].cpu, n["N2"].battery_wh) == (2.0, None)  # null overrides: wall power
    assert n["N3"].power == PowerModel(idle_w=0.5, cpu_w=9.0)
    assert sc.network.link("N1", "N2") == LinkSpec("N1", "N2", None, 2.0, 0.1)
    assert sc.network.link("N2", "N3") == LinkSpec("N2", "N3", None, 2.0, 0.0)


# -- errors ---------------------------------------------------------------------------------


def test_unknown_node_in_link() -> None:
    err = scenario_error(
        """
        nodes:
          N1: {}
          N2: {}
        links:
          - [N1, N2]
          - [N2, N9]
        """
    )
    assert_at(err, 6, "links[1]", "unknown node 'N9' (known: N1, N2)")
    err = scenario_error(
        """
        nodes:
          N1: {}
          N2: {}
        links:
          - delay_ms: 1
            between: [N7, N2]
        """
    )
    assert_at(err, 6, "links[0].between", "unknown node 'N7'")


@pytest.mark.parametrize(
    ("value", "shown"), [("0", "0"), ("-1", "-1"), ("true", "True"), ("fast", "'fast'")]
)
def test_non_positive_cpu(value: str, shown: str) -> None:
    err = scenario_error(
        f"""
        nodes:
          N1: {{}}
          N2:
            battery_wh: 3
            cpu: {value}
        """
    )
    assert_at(err, 5, "nodes.N2.cpu", f"expected a number > 0, got {shown}")


@pytest.mark.parametrize(
    ("text", "line", "field"),
    [
        ("nodes:\n  N1: {}\nlinkz: []\n", 3, "linkz"),
        ("nodes:\n  N1:\n    cpu: 1\n    speed: 2\n", 4, "nodes.N1.speed"),
        ("nodes:\n  N1: {power: {idle: 1}}\n", 2, "nodes.N1.power.idle"),
        ("node_defaults:\n  pos: [0, 0]\nnodes:\n  N1: {}\n", 2, "node_defaults.pos"),
        ("link_defaults:\n  between: [A, B]\nnodes:\n  N1: {}\n", 2, "link_defaults.between"),
        (
            "nodes:\n  N1: {}\n  N2: {}\nlinks:\n  - between: [N1, N2]\n    latency: 3\n",
            6,
            "links[0].latency",
        ),
    ],
)
def test_unknown_attribute(text: str, line: int, field: str) -> None:
    err = scenario_error(text)
    assert_at(err, line, field, f"unknown attribute {field.rsplit('.', 1)[-1]!r}")
    assert "(expected one of: " in err.message


@pytest.mark.parametrize("loss", ["1", "1.0", "1.5"])
def test_loss_of_one_or_more(loss: str) -> None:
    err = scenario_error(
        f"""
        nodes:
          N1: {{}}
          N2: {{}}
        links:
          - between: [N1, N2]
            loss: {loss}
        """
    )
    assert_at(err, 6, "links[0].loss", "expected a loss probability in [0, 1)")
    err = scenario_error(
        f"""
        link_defaults:
          loss: {loss}
        nodes:
          N1: {{}}
        """
    )
    assert_at(err, 2, "link_defaults.loss", "expected a loss probability in [0, 1)")


def test_negative_loss() -> None:
    err = scenario_error(
        "nodes:\n  N1: {}\n  N2: {}\nlinks:\n  - {between: [N1, N2], loss: -0.1}\n"
    )
    assert_at(err, 5, "links[0].loss", "expected a number >= 0, got -0.1")


def test_missing_pos_with_radio_range() -> None:
    err = scenario_error(
        """
        radio_range: 50
        nodes:
          A: {pos: [0, 0]}
          B: {cpu: 2}
        """
    )
    assert_at(err, 4, "nodes.B", "a node needs 'pos: [x, y]' when the scenario has a radio_range")


def test_links_and_radio_range_together() -> None:
    err = scenario_error(
        """
        nodes:
          A: {pos: [0, 0]}
          B: {pos: [1, 0]}
        radio_range: 50
        links:
          - [A, B]
        """
    )
    assert_at(err, 4, "radio_range", "give either 'links' or 'radio_range', not both")


@pytest.mark.parametrize(
    ("text", "line", "field", "phrase"),
    [
        ("radio_range: 0\nnodes:\n  A: {pos: [0, 0]}\n", 1, "radio_range", "number > 0"),
        ("nodes:\n  A: {pos: [0]}\n", 2, "nodes.A.pos", "expected a position [x, y]"),
        ("nodes:\n  A: {}\nlinks:\n  - [A, A]\n", 4, "links[0]", "two different nodes"),
        ("nodes:\n  A: {}\n  B: {}\nlinks:\n  - [A, B]\n  - [B, A]\n", 6, "links[1]", "duplicate"),
        ("nodes:\n  A: {}\nlinks:\n  - [A]\n", 4, "links[0]", "a pair of node ids"),
        ("nodes:\n  A: {}\nlinks: [A, B]\n", 3, "links[0]", "expected a mapping, got 'A'"),
        ("nodes:\n  A: {}\nlinks: {A: B}\n", 3, "links", "expected a list of links"),
        ("nodes: {}\n", 1, "nodes", "non-empty mapping of node id"),
        ("name: x\n", 1, "nodes", "non-empty mapping of node id"),
        ("nodes:\n  A: {battery_wh: 0}\n", 2, "nodes.A.battery_wh", "number > 0"),
        ("nodes:\n  A: {power: {cpu_w: -1}}\n", 2, "nodes.A.power.cpu_w", "number >= 0"),
        ("nodes:\n  A: 5\n", 2, "nodes.A", "expected a mapping, got 5"),
        ("nodes: {A: {}}\nchanges:\n  - {at: 1, fail: B}\n", 3, "changes[0].fail", "unknown node"),
        (
            "nodes: {A: {}, B: {}}\nchanges:\n  - {at: 1, fail: A, down: [A, B]}\n",
            3,
            "changes[0]",
            "exactly one of 'up', 'down', 'fail', 'restart', 'partition', 'heal', 'loss'",
        ),
        ("nodes: {A: {}}\nchanges:\n  - {at: 1, restart: Z}\n", 3, "changes[0].restart", "unknown"),
        (
            "nodes: {A: {}, B: {}}\nchanges:\n  - {at: 1, partition: [[A], [A, B]]}\n",
            3,
            "changes[0].partition[1]",
            "node 'A' is in two groups",
        ),
        (
            "nodes: {A: {}, B: {}}\nchanges:\n  - {at: 1, partition: [[A, B]]}\n",
            3,
            "changes[0].partition",
            "at least two groups",
        ),
        (
            "nodes: {A: {}, B: {}}\nchanges:\n  - {at: 1, partition: [A, B]}\n",
            3,
            "changes[0].partition",
            "list of node groups",
        ),
        ("nodes: {A: {}}\nchanges:\n  - {at: 1, heal: no}\n", 3, "changes[0].heal", "heal: true"),
        ("nodes: {A: {}}\nchanges:\n  - {at: 1, loss: 1.0}\n", 3, "changes[0].loss", "[0, 1)"),
        (
            "nodes: {A: {}, B: {}}\nchanges:\n  - {at: 1, loss: 0.1, between: [A, C]}\n",
            3,
            "changes[0].between",
            "unknown node 'C'",
        ),
        (
            "nodes: {A: {}, B: {}}\nchanges:\n  - {at: 1, down: [A, B], between: [A, B]}\n",
            3,
            "changes[0].between",
            "goes with 'loss' only",
        ),
        ("nodes: {A: {}}\nchanges:\n  - {at: -1, heal: true}\n", 3, "changes[0].at", ">= 0"),
    ],
)
def test_other_scenario_errors(text: str, line: int, field: str, phrase: str) -> None:
    assert_at(scenario_error(text), line, field, phrase)


@pytest.mark.parametrize("text", ["", "# nothing\n"])
def test_empty_scenario(text: str) -> None:
    err = scenario_error(text)
    assert_at(err, None, None, "expected a mapping with 'name' and 'nodes'")


def test_duplicate_node_is_a_located_error() -> None:
    err = scenario_error("nodes:\n  A: {}\n  A: {cpu: 2}\n")
    assert (err.file, err.line, err.field) == (FILE, 3, "nodes.A")
    assert "duplicate key 'A'" in err.message


def test_bad_node_default_points_at_node_defaults() -> None:
    err = scenario_error(
        """
        node_defaults:
          cpu: 0
        nodes:
          N1: {}
        """
    )
    assert_at(err, 2, "node_defaults.cpu", "expected a number > 0")


# -- routes ---------------------------------------------------------------------------------


def test_mesh_tie_break_by_node_order() -> None:
    # A square A-B-D, A-C-D: two shortest routes; the node declared first wins.
    links = [("A", "B"), ("A", "C"), ("B", "D"), ("C", "D")]
    net = network(["A", "B", "C", "D"], links)
    assert net.route("A", "D") == ["A", "B", "D"]
    assert net.route("D", "A") == ["D", "B", "A"]
    assert net.next_hop("A", "D") == "B"
    net = network(["A", "C", "B", "D"], links)
    assert net.route("A", "D") == ["A", "C", "D"]
    assert net.next_hop("A", "D") == "C"
    # Declaring links in another order changes nothing.
    net = network(["A", "B", "C", "D"], list(reversed(links)))
    assert net.route("A", "D") == ["A", "B", "D"]


def test_remove_link_reroutes_and_add_link_restores() -> None:
    net = network(
        ["A", "B", "C", "D", "E"],
        [("A", "B"), ("B", "E"), ("A", "C"), ("C", "D"), ("D", "E")],
    )
    assert net.route("A", "E") == ["A", "B", "E"]
    assert net.next_hop("A", "E") == "B"
    net.remove_link("E", "B")  # either order of the ends
    assert net.link("B", "E") is None
    assert net.route("A", "E") == ["A", "C", "D", "E"]
    assert net.next_hop("A", "E") == "C" and net.hops("A", "E") == 3
    assert net.neighbours("B") == ["A"]
    net.remove_link("B", "E")  # already gone: no-op
    net.remove_link("A", "C")
    assert net.route("A", "E") is None and net.next_hop("A", "E") is None
    assert net.hops("A", "E") is None
    assert net.route("A", "B") == ["A", "B"]
    net.add_link(LinkSpec("B", "E"))
    assert net.route("A", "E") == ["A", "B", "E"]


def test_network_rejects_bad_links() -> None:
    with pytest.raises(ValueError, match="unknown node 'Z'"):
        network(["A"], [("A", "Z")])
    with pytest.raises(ValueError, match="itself"):
        network(["A"], [("A", "A")])
    with pytest.raises(ValueError, match="duplicate node id"):
        Network([NodeSpec("A"), NodeSpec("A")])


@st.composite
def connected_networks(draw: st.DrawFn) -> Network:
    n = draw(st.integers(1, 12))
    ids = [f"N{i}" for i in draw(st.permutations(range(n)))]
    links = {(ids[draw(st.integers(0, i - 1))], ids[i]) for i in range(1, n)}
    if n >= 2:
        extra = st.tuples(st.integers(0, n - 1), st.integers(0, n - 1))
        for a, b in draw(st.lists(extra, max_size=2 * n)):
            if a != b and (ids[b], ids[a]) not in links:
                links.add((ids[a], ids[b]))
    return network(ids, sorted(links))


@settings(max_examples=80, deadline=None)
@given(connected_networks(), st.data())
def test_routes_are_shortest_and_hop_by_hop_consistent(net: Network, data: st.DataObject) -> None:
    ids = list(net.nodes)
    src = data.draw(st.sampled_from(ids))
    dst = data.draw(st.sampled_from(ids))
    route = net.route(src, dst)
    assert route is not None and route[0] == src and route[-1] == dst
    assert len(route) - 1 == net.distances(src)[dst] == net.hops(src, dst)
    assert len(set(route)) == len(route)
    for a, b in itertools.pairwise(route):
        assert net.link(a, b) is not None
    # Forwarding hop by hop along next_hop follows exactly this route.
    if src != dst:
        assert net.next_hop(src, dst) == route[1]
        assert net.route(route[1], dst) == route[1:]


def test_scripted_failures_and_link_changes_in_time_order() -> None:
    sc = loads_scenario(
        yml("""
        nodes: {A: {}, B: {}, C: {}}
        links: [[A, B], [B, C]]
        changes:
          - {at: 5, fail: B}
          - {at: 2, down: [A, B]}
        """)
    )
    assert sc.changes == [
        LinkChange(at=2, a="A", b="B", up=False, link=sc.network.link("A", "B")),
        NodeFailure(at=5, node="B"),
    ]


def test_restarts_partitions_heals_and_loss_changes_parse() -> None:
    sc = loads_scenario(
        yml("""
        nodes: {A: {}, B: {}, C: {}}
        links: [[A, B], [B, C]]
        changes:
          - {at: 9, heal: true}
          - {at: 3, partition: [[A], [B]]}
          - {at: 2, restart: B}
          - {at: 4, loss: 0.25, between: [B, C]}
          - {at: 4, loss: 0.1}
        """)
    )
    assert sc.changes == [
        NodeRestart(at=2, node="B"),
        Partition(at=3, groups=(frozenset({"A"}), frozenset({"B"}))),
        LossChange(at=4, loss=0.25, ends=("B", "C")),
        LossChange(at=4, loss=0.1, ends=None),
        Heal(at=9),
    ]
