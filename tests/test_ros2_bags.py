"""Bags: the shipped generated bag replays in order at its recorded timing (or faster), and a
BagSink's recording replays as the same messages, in order — also as an mso app in the
simulator (BagSource -> BagSink)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from make_ros2_bag import BAG, COUNT, texts
from mso.ros2 import BagSink, BagSource
from mso.ros2.types import struct_for
from mso.sim.runner import Simulation
from test_runtime_sim import deploy, line

String = struct_for("std_msgs/msg/String")


def replay(path: Path | str, **params: object) -> list[object]:
    src = BagSource(str(path), **params)  # type: ignore[arg-type]
    src.open()
    try:
        return [e for e in src if e is not None]
    finally:
        src.close()


def test_the_shipped_bag_replays_in_order() -> None:
    assert replay(BAG, rate=0) == [String(data=t) for t in texts()]
    assert replay(BAG / "ros2_chatter.mcap", topics=["chatter"], rate=0)[0] == String(
        data="hello world 0"
    )


def test_rate_scales_the_recorded_timing() -> None:
    t0 = time.monotonic()
    assert len(replay(BAG, rate=10)) == COUNT  # 1.9 s recorded, 0.19 s at 10x
    took = time.monotonic() - t0
    assert 0.17 <= took < 1.5


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_recording_replays_as_the_same_messages(tmp_path: Path, storage: str) -> None:
    sink = BagSink(str(tmp_path / "rec"), "/out", "std_msgs/msg/String", storage=storage)
    sink.open()
    sent = [String(data=f"m{i}") for i in range(50)]
    for ev in sent:
        sink(ev)
    sink.end()
    suffix = ".mcap" if storage == "mcap" else ".db3"
    assert any(p.suffix == suffix for p in (tmp_path / "rec").iterdir())
    assert replay(tmp_path / "rec", rate=0) == sent
    with pytest.raises(Exception):  # noqa: B017 - rosbags refuses to overwrite a bag
        BagSink(str(tmp_path / "rec"), "/out", "std_msgs/msg/String").open()


def test_a_bag_source_of_mixed_types_asks_for_topics(tmp_path: Path) -> None:
    sink = BagSink(str(tmp_path / "b"), "/scan", "sensor_msgs/msg/LaserScan")
    sink.open()
    sink({"ranges": [1.0, 2.0]})
    sink.close()
    assert replay(tmp_path / "b", rate=0)[0].ranges == [1.0, 2.0]  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="not std_msgs"):
        replay(tmp_path / "b", type="std_msgs/msg/String")


def test_bag_to_bag_as_an_mso_app(tmp_path: Path) -> None:
    out = tmp_path / "copy"
    app = f"""
name: bagcopy
vertices:
  play: {{code: "mso.ros2:BagSource", pinned: N1, params: {{path: "{BAG}", rate: 0}},
         output: "mso.ros2.types:std_msgs__msg__String"}}
  loud: {{code: "ros2_vertices:shout", output: "mso.ros2.types:std_msgs__msg__String"}}
  rec: {{code: "mso.ros2:BagSink", pinned: N3,
         params: {{path: "{out}", topic: /loud, type: std_msgs/msg/String}}}}
edges: [[play, loud], [loud, rec]]
"""
    sim = Simulation(line(3))
    assert deploy(sim, app).ok
    sim.run_until(sim.now + 3.0)
    rec = sim.instance("N3", "bagcopy", "rec")
    assert rec.written == COUNT and rec.writer is None  # end() closed the bag
    assert replay(out, rate=0) == [String(data=t.upper()) for t in texts()]
