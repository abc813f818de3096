"""The dashboard: its view of status replies (pure), and its server against a running emulation
of the convoy (the page, the event stream, the controls, and what it refuses)."""

from __future__ import annotations

import itertools
import json
import math
import os
import shutil
import subprocess
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dashboard_live import EXAMPLES, KEY, POSITIONS, LiveDashboard, start_live
from mso.dashboard.view import MOVED_S, Tracker, movable
from mso.model.appfile import loads_app
from mso.model.chains import form_chains


def status(placement: dict[str, str], delivered: int, *, done: list[str] | None = None,
           dropped: int = 0, failed: list[str] | None = None) -> dict[str, Any]:  # fmt: skip
    """A two-node status reply: src -> mid -> sink, one chain."""
    nodes: dict[str, Any] = {}
    for nid in ("N1", "N2"):
        here = {v: n for v, n in placement.items() if n == nid}
        nodes[nid] = {
            "node": nid,
            "neighbours": ["N2" if nid == "N1" else "N1"],
            "routes": {},
            "failed_nodes": failed or [],
            "failures": [{"node": f, "detector": "N1", "at": 1.0} for f in failed or []],
            "rejoins": [],
            "management": {"done": done or [] if nid == "N1" else []},
            "monitor": {"battery_fraction": 0.5, "drain_w": 2.0, "lifetime_s": 100.0, "load": 0.1},
            "traffic": {"bytes_in": delivered * 10, "bytes_out": 0, "bytes_forwarded": 0},
            "apps": {
                "pipe": {
                    "chains": [["src", "mid", "sink"]],
                    "chain_delay_ms": {"src-mid-sink": 1.5},
                    "parked": {},
                    "given_up": {"src->mid": dropped} if nid == "N1" else {},
                    "recoveries": [],
                    "vertices": {
                        v: {"kind": "operator", "processed": 0, "emitted": 0, "cpu_s": 0.0}
                        for v in here
                    },
                    "edges": {"mid->sink": {"delivered": delivered}} if "sink" in here else {},
                }
            },
        }
    return nodes


def test_tracker_rates_moves_and_reasons() -> None:
    tr = Tracker(t0=100.0)
    first = tr.update(status({"src": "N1", "mid": "N1", "sink": "N2"}, 100), 101.0)
    chain = first["apps"][0]["chains"][0]
    assert chain["events_per_s"] is None  # no rate from one reply
    assert chain["nodes"] == ["N1", "N1", "N2"] and chain["colour"].startswith("#")
    assert first["links"] == [["N1", "N2"]] and first["timeline"] == []
    second = tr.update(
        status({"src": "N1", "mid": "N2", "sink": "N2"}, 300, dropped=3,
               done=["103.0 remap pipe chain 0 (route changed)"]),
        103.0,
    )  # fmt: skip
    assert second["apps"][0]["chains"][0]["events_per_s"] == pytest.approx(100.0)
    assert second["nodes"][0]["traffic"]["bytes_in"] == pytest.approx(1000.0)
    kinds = {e["kind"]: e for e in second["timeline"]}
    assert kinds["move"]["what"] == "mid: N1 → N2" and kinds["move"]["lost"] == 3
    assert kinds["rule"]["what"] == "N1: remap pipe chain 0"
    assert kinds["rule"]["why"] == "route changed"
    # asked for: the reply comes after status showed the move, and names it
    tr.attribute(103.5, "pipe", "mid", "N2", "relocation", "asked from the dashboard", 4.2)
    latest = tr.update(status({"src": "N1", "mid": "N2", "sink": "N2"}, 400), 104.0)
    move = next(e for e in latest["timeline"] if e["what"] == "mid: N1 → N2")
    assert (move["kind"], move["took_ms"], move["why"]) == (
        "relocation",
        4.2,
        "asked from the dashboard",
    )
    assert len([e for e in latest["timeline"] if e["kind"] == "rule"]) == 1  # not repeated
    # the reply first, the move after
    tr.attribute(104.5, "pipe", "mid", "N1", "relocation", "asked from the dashboard", 7.0)
    after = tr.update(status({"src": "N1", "mid": "N1", "sink": "N2"}, 500), 105.0)
    assert after["timeline"][0]["what"] == "mid: N2 → N1" and after["timeline"][0]["took_ms"] == 7.0


def test_tracker_names_the_rule_that_moved_a_vertex() -> None:
    tr = Tracker(t0=0.0)
    tr.update(status({"src": "N1", "mid": "N1", "sink": "N2"}, 0), 1.0)
    decision = "1.5 relocate pipe/mid -> N2 (lifetime, downstream: 26% better)"
    view = tr.update(status({"src": "N1", "mid": "N1", "sink": "N2"}, 0, done=[decision]), 2.0)
    assert view["timeline"] == []  # decided, not yet moved
    view = tr.update(status({"src": "N1", "mid": "N2", "sink": "N2"}, 0, done=[decision]), 3.0)
    (entry,) = view["timeline"]
    assert entry["kind"] == "relocation" and entry["what"] == "mid: N1 → N2"
    assert entry["why"] == "rule on N1: lifetime, downstream: 26% better" and entry["lost"] == 0
    # a later move nobody announced is not blamed on that rule
    view = tr.update(status({"src": "N1", "mid": "N1", "sink": "N2"}, 0, done=[decision]), 4.0)
    assert view["timeline"][0]["kind"] == "move"


def test_a_node_that_stops_answering_keeps_its_last_battery() -> None:
    tr = Tracker(t0=0.0)
    tr.update(status({"src": "N1", "mid": "N1", "sink": "N2"}, 0), 1.0, expected=["N1", "N2"])
    nodes = status({"src": "N1", "mid": "N1", "sink": "N2"}, 0, failed=["N2"])
    del nodes["N2"]
    view = tr.update(nodes, 2.0, expected=["N1", "N2"])
    n2 = next(n for n in view["nodes"] if n["id"] == "N2")
    assert not n2["answered"] and n2["failed"] and n2["last_battery"] == 0.5


def test_only_a_chains_interior_is_offered_with_the_ways_it_can_go() -> None:
    chains = [["cam", "scale", "edges", "track"], ["track", "log"], ["imu", "track"]]
    placement = {"cam": "R1", "scale": "R1", "edges": "R2", "track": "R2", "log": "R3",
                 "imu": "R1"}  # fmt: skip
    # heads, tails and the join (track) never; scale can go downstream only (cam is beside it)
    assert movable(chains, placement) == {"edges": ["upstream"], "scale": ["downstream"]}


def test_a_moved_vertex_is_flagged_for_a_while_and_chains_keep_a_history() -> None:
    tr = Tracker(t0=0.0)
    tr.update(status({"src": "N1", "mid": "N1", "sink": "N2"}, 0), 1.0)
    view = tr.update(status({"src": "N1", "mid": "N2", "sink": "N2"}, 100), 2.0)
    assert view["apps"][0]["moved"] == {"mid": 0.0}
    later = tr.update(status({"src": "N1", "mid": "N2", "sink": "N2"}, 200), 2.0 + MOVED_S)
    assert later["apps"][0]["moved"] == {}
    history = later["apps"][0]["chains"][0]["history"]
    assert [h[0] for h in history] == [1.0, 2.0, 2.0 + MOVED_S]  # t, events/s, delay ms
    assert history[0][1] is None and history[1][1] == pytest.approx(100.0)
    assert all(h[2] == 1.5 for h in history)


def test_a_recoverys_moves_seen_before_its_record_are_shown_after_it_as_its_own() -> None:
    """The restored vertex runs at its new host (status shows the move) a poll before the
    coordinator's record says the recovery is done: the timeline still tells the recovery
    first, then the move it made, worded as the recovery's."""
    tr = Tracker(t0=0.0)
    tr.update(status({"src": "N1", "mid": "N2", "sink": "N2"}, 0), 1.0)
    nodes = status({"src": "N1", "mid": "N1", "sink": "N2"}, 0, failed=["N2"])
    record = {"at": 1.5, "failed": ["N2"], "remap": "chain", "chains": ["src-mid-sink"],
              "lost": ["mid"]}  # fmt: skip
    nodes["N1"]["apps"]["pipe"]["recoveries"] = [record]  # under way: not done yet
    timeline = tr.update(nodes, 2.0)["timeline"]
    assert [(e["kind"], e["what"]) for e in timeline if e["kind"] != "failure"] == [
        ("move", "mid: N2 → N1")
    ]
    nodes["N1"]["apps"]["pipe"]["recoveries"] = [record | {"ok": True, "took_ms": 4.0}]
    timeline = tr.update(nodes, 3.0)["timeline"]  # newest first
    newest, oldest = (e for e in timeline if e["kind"] != "failure")
    assert (oldest["kind"], oldest["what"], oldest["why"]) == (
        "recovery",
        "pipe: chain remap of src-mid-sink",
        "N2 failed",
    )
    assert (newest["kind"], newest["what"], newest["why"]) == (
        "recovery",
        "mid: N2 → N1",
        "N2 failed",
    )
    assert oldest["t"] == newest["t"] == 2.0  # the recovery shown when its move was seen


def test_tracker_failed_and_silent_nodes() -> None:
    tr = Tracker(t0=0.0)
    nodes = status({"src": "N1", "mid": "N1", "sink": "N2"}, 0, failed=["N3"])
    view = tr.update(nodes, 1.0, positions={"N1": (0.0, 0.0)}, expected=["N1", "N2", "N3"])
    n3 = next(n for n in view["nodes"] if n["id"] == "N3")
    assert n3 == {"id": "N3", "answered": False, "failed": True, "unreachable": False,
                  "last_battery": None, "pos": None}  # fmt: skip
    assert view["nodes"][0]["pos"] == [0.0, 0.0]
    assert view["failed"] == ["N3"]
    assert [e["what"] for e in view["timeline"]] == ["N3 failed"]


@pytest.fixture(scope="module")
def live() -> Iterator[LiveDashboard]:
    board = start_live()
    try:
        yield board
    finally:
        board.stop()


def get(url: str, headers: dict[str, str] | None = None) -> tuple[int, bytes]:
    req = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def post(url: str, body: bytes, headers: dict[str, str]) -> tuple[int, dict[str, Any]]:
    req = urllib.request.Request(url, data=body, headers=headers, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def convoy_chains() -> int:
    """How many chains the bundled convoy forms (the dashboard shows each)."""
    app = loads_app((EXAMPLES / "convoy.yaml").read_text(), file="convoy.yaml")
    return len(form_chains(app))


@pytest.mark.slow
def test_page_stream_and_state_never_show_the_key(live: LiveDashboard) -> None:
    seen = b""
    for path in ("", "static/app.js", "static/style.css", "api/view"):
        code, body = get(live.url + path)
        assert code == 200, path
        seen += body
    with urllib.request.urlopen(live.url + "events", timeout=10) as stream:
        assert stream.headers["Content-Type"] == "text/event-stream"
        line = b""
        while not line.startswith(b"data: "):
            line = stream.readline()
    view = json.loads(line[6:])
    assert sorted(n["id"] for n in view["nodes"]) == ["N1", "N2", "N3", "N4"]
    assert len(view["apps"][0]["chains"]) == convoy_chains()
    seen += line + live.state_file.read_bytes()
    assert KEY.encode() not in seen and b"MSO_KEY" not in seen


@pytest.mark.slow
def test_requests_from_elsewhere_are_refused(live: LiveDashboard) -> None:
    assert get(live.url + "api/view", {"Host": "attacker.example:80"})[0] == 403
    assert get(live.url + "nowhere")[0] == 404
    ok = {"Content-Type": "application/json"}
    body = json.dumps({"app": "convoy", "vertex": "scan_matcher", "target": "N2"}).encode()
    code, answer = post(live.url + "api/relocate", body, ok | {"Origin": "http://attacker.example"})
    assert code == 403 and "dashboard's own page" in answer["error"]
    assert post(live.url + "api/relocate", body, {"Content-Type": "text/plain"})[0] == 415
    code, answer = post(live.url + "api/relocate", b'{"app": "convoy"}', ok)
    assert code == 400 and answer["error"] == "vertex: expected a non-empty string"
    code, answer = post(live.url + "api/remap", b'{"app": "convoy", "chains": ["x"]}', ok)
    assert code == 400 and "chain indices" in answer["error"]
    code, answer = post(live.url + "api/relocate", b'{"app": "convoy", "vertex": "nope",'
                        b' "direction": "upstream"}', ok)  # fmt: skip
    assert code == 409 and answer["ok"] is False and answer["error"]


@pytest.mark.slow
def test_relocation_from_the_page_shows_on_the_timeline(live: LiveDashboard) -> None:
    placement = live.view()["apps"][0]["placement"]
    target = "N2" if placement["scan_matcher"] == "N1" else "N1"
    code, answer = post(
        live.url + "api/relocate",
        json.dumps({"app": "convoy", "vertex": "scan_matcher", "target": target}).encode(),
        {"Content-Type": "application/json", "Origin": live.url.rstrip("/")},
    )
    assert code == 200 and answer["node"] == target, answer
    view = live.wait_for(lambda v: v["apps"][0]["placement"]["scan_matcher"] == target)
    entry = next(e for e in view["timeline"] if e["what"].startswith("scan_matcher:"))
    assert entry["kind"] == "relocation" and entry["why"] == "asked from the dashboard"
    assert entry["took_ms"] == pytest.approx(answer["elapsed_ms"], abs=0.01)
    assert entry["lost"] == 0


CHROMIUM = Path("/usr/bin/chromium")  # Debian's; never a browser build downloaded by a tool
ARTEFACTS = Path(os.environ.get("MSO_TEST_ARTIFACTS", Path(__file__).parents[1] / "test-artifacts"))


def system_chromium() -> Path:
    """Debian's chromium, installed here if missing and we may (root, as in CI)."""
    if not CHROMIUM.exists() and os.geteuid() == 0 and shutil.which("apt-get"):
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        for cmd in (["apt-get", "install", "-y", "-q", "chromium"], ["apt-get", "update", "-q"],
                    ["apt-get", "install", "-y", "-q", "chromium"]):  # fmt: skip
            subprocess.run(cmd, env=env, capture_output=True, timeout=900, check=False)
            if CHROMIUM.exists():
                break
    if not CHROMIUM.exists():
        pytest.skip(
            "needs Debian's chromium at /usr/bin/chromium, which could not be installed here "
            "(not root, or no apt-get): run `apt-get install chromium` (make test does, as root)"
        )
    return CHROMIUM


# heights on the page: the topology panel, its svg, and what is drawn in it (robots with their
# labels, chains), as laid out
FILL_JS = """() => {
  const svg = document.getElementById("topology");
  const drawn = [...svg.querySelectorAll("g.node, polyline")].map((e) => e.getBoundingClientRect());
  const top = Math.min(...drawn.map((r) => r.top));
  const bottom = Math.max(...drawn.map((r) => r.bottom));
  return { panel: document.getElementById("topology-panel").getBoundingClientRect().height,
           svg: svg.getBoundingClientRect().height, drawn: bottom - top };
}"""


@pytest.mark.slow
def test_dashboard_in_a_real_browser(live: LiveDashboard) -> None:
    """Headless Chromium loads the page, sees every node and chain, relocates a vertex with
    the controls and sees its mapping change; the screenshot is kept as a test artefact."""
    from playwright.sync_api import expect, sync_playwright

    chromium = system_chromium()
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    errors: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=str(chromium), headless=True, args=["--no-sandbox"]
        )
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.on("console", lambda msg: errors.append(msg.text) if msg.type == "error" else None)
            page.goto(live.url)
            expect(page.locator("#conn")).to_have_text("live")
            for n in ("N1", "N2", "N3", "N4"):
                expect(page.locator(f'#nodes tr[data-node="{n}"]')).to_be_visible()
                expect(page.locator(f'#topology g[data-node="{n}"]')).to_be_visible()
            expect(page.locator("#chains tbody tr")).to_have_count(convoy_chains())
            expect(page.locator("#topology polyline")).not_to_have_count(0)
            # laid out from the scenario's positions: left to right, N2 and N4 off N1's row
            centres = {
                n: (
                    float(
                        page.locator(f'#topology g[data-node="{n}"] circle.robot').get_attribute(
                            "cx"
                        )
                    ),
                    float(
                        page.locator(f'#topology g[data-node="{n}"] circle.robot').get_attribute(
                            "cy"
                        )
                    ),
                )
                for n in POSITIONS
            }
            xs = [centres[n][0] for n in sorted(POSITIONS, key=lambda n: POSITIONS[n][0])]
            assert xs == sorted(xs) and len(set(xs)) == 4, centres
            # N2 and N4 (40 m off the line) drawn below N1 and N3; robots closer than their
            # labels need are pushed apart, by as much as the panel's size at that moment
            # makes them close, so N1 and N3 need not share a row exactly
            ys = {n: c[1] for n, c in centres.items()}
            assert min(ys["N2"], ys["N4"]) > max(ys["N1"], ys["N3"]), centres
            # each chain is drawn along the route its events take: hop by hop over the line's
            # links, through the relays (no straight stroke from N1 to N3)
            links = {("N1", "N2"), ("N2", "N3"), ("N3", "N4")}
            lines = page.locator("#topology polyline")
            for i in range(lines.count()):
                points = [
                    tuple(map(float, p.split(",")))
                    for p in (lines.nth(i).get_attribute("points") or "").split()
                ]
                at = [  # robots are at least 130 apart: the one within 65 of a point is its
                    next(n for n, c in centres.items() if math.dist(c, (x, y)) < 65)
                    for x, y in points
                ]
                assert all(tuple(sorted(p)) in links for p in itertools.pairwise(at)), at
            expect(page.locator('#nodes tr[data-node="N1"] td').nth(2)).to_contain_text("%")
            cell = page.locator('#chains tr[data-chain="0"] span[data-vertex="scan_matcher"]')
            before = cell.get_attribute("data-node")
            target = "N2" if before == "N1" else "N1"
            page.select_option("#app", "convoy")
            page.select_option("#relocate-vertex", "scan_matcher")
            page.select_option("#relocate-target", f"node:{target}")
            page.click("#relocate-go")
            expect(page.locator("#control-result")).to_contain_text(f"now runs on {target}")
            expect(cell).to_have_attribute("data-node", target, timeout=15_000)
            expect(cell).to_have_text(f"scan_matcher@{target}")
            row = page.locator('#timeline tr[data-kind="relocation"]').first
            expect(row).to_contain_text(f"scan_matcher: {before} → {target}")
            expect(row).to_contain_text("none")  # events lost
            # only what a relocation can move is offered: never a chain's pinned head or tail
            offered = page.locator("#relocate-vertex option").evaluate_all(
                "os => os.map(o => o.value)"
            )
            assert "scan_matcher" in offered and not {"laser", "storage", "localization"} & set(
                offered
            ), offered
            # the reconfigurations are in view beside the topology at both sizes shot for docs
            for w, h in ((1280, 800), (1920, 1080)):
                page.set_viewport_size({"width": w, "height": h})
                for panel in ("#topology-panel", "#timeline-panel", "#controls-panel"):
                    box = page.locator(panel).bounding_box()
                    assert box is not None and box["y"] + 60 < h and box["x"] < w, (w, panel, box)
                # and the drawing fills its panel: the svg most of the panel's height, the
                # robots, labels and chains most of the svg's (it was a strip over an empty box)
                fill = page.evaluate(FILL_JS)
                assert fill["svg"] > 0.6 * fill["panel"], (w, fill)
                assert fill["drawn"] > 0.45 * fill["svg"], (w, fill)
            page.screenshot(path=str(ARTEFACTS / "dashboard.png"), full_page=True)
        finally:
            browser.close()
    assert not errors, errors
    assert (ARTEFACTS / "dashboard.png").stat().st_size > 10_000


def test_tracker_tells_who_asked_for_a_move_from_the_nodes_records() -> None:
    tr = Tracker(t0=0.0)
    tr.update(status({"src": "N1", "mid": "N1", "sink": "N2"}, 0), 1.0)
    nodes = status({"src": "N1", "mid": "N2", "sink": "N2"}, 0)
    nodes["N1"]["moves"] = [
        {"seq": 1, "what": "relocation", "app": "pipe", "vertex": "mid", "detail": "N1 -> N2",
         "by": "operator", "asked": "an operator (mso relocate)", "took_ms": 3.5, "error": "",
         "ago_s": 0.4},
    ]  # fmt: skip
    (entry,) = tr.update(nodes, 2.0)["timeline"]
    assert (entry["what"], entry["why"], entry["took_ms"]) == (
        "mid: N1 → N2",
        "an operator (mso relocate)",
        3.5,
    )


def test_a_page_is_told_when_the_run_ends() -> None:
    """Stopping the dashboard sends each open page a last view that says the run ended (the
    page then shows "ended" and stops reconnecting), then closes the stream."""
    import asyncio

    from mso.dashboard.server import Dashboard

    async def run() -> bytes:
        board = Dashboard(["127.0.0.1:9"], "k", name="gone", interval=0.2)  # nothing listens
        url = await board.start()
        reader, writer = await asyncio.open_connection(board.host, board.port)
        writer.write(f"GET /events HTTP/1.1\r\nHost: {url.split('/')[2]}\r\n\r\n".encode())
        await writer.drain()
        await reader.readuntil(b"retry: 2000\n\n")
        await board.wait_update(10.0)
        await board.stop()
        got = await asyncio.wait_for(reader.read(), 10.0)  # to the end of the stream
        writer.close()
        return got

    events = [e for e in asyncio.run(run()).split(b"\n\n") if e.startswith(b"data: ")]
    last = json.loads(events[-1].removeprefix(b"data: "))
    assert last["ended"] is True and last["overlay"] == "gone"
    assert not any(json.loads(e.removeprefix(b"data: "))["ended"] for e in events[:-1])


def test_a_vertex_failing_on_every_event_is_flagged() -> None:
    tr = Tracker(t0=0.0)
    placement = {"src": "N1", "mid": "N1", "sink": "N2"}

    def failing(errors: int) -> dict[str, Any]:
        nodes = status(placement, 0)
        mid = nodes["N1"]["apps"]["pipe"]["vertices"]["mid"]
        mid.update(errors=errors, last_error="mid: returned dict, expected Num")
        return nodes

    assert tr.update(failing(0), 1.0)["apps"][0]["alarms"] == []
    (alarm,) = tr.update(failing(20), 3.0)["apps"][0]["alarms"]  # 10 a second
    assert alarm == {"vertex": "mid", "node": "N1", "errors": 20, "per_s": 10.0,
                     "last_error": "mid: returned dict, expected Num"}  # fmt: skip
    assert tr.update(failing(20), 9.0)["apps"][0]["alarms"] == []  # it stopped failing
