"""How far any static placement can lower the leader's draw in the energy study (app
accounting): every combination of the leader-side vertices on or off the leader (scan filter,
scan matcher, odometry filter; blob detectors, fusion, the target map's pipeline), the rest
where Algorithm 1 puts it, each run 120 s of virtual time. Localization, planning and the rest
on the leader would only add to its draw, so the lowest draw bounds the leader's lifetime
against Algorithm 1 kept for good under any placement, static or moved by rules.

    .venv/bin/python bench/lifetime_floor.py [--seconds 120] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from pathlib import Path

from mso.benchmarks import lifetime as study
from mso.benchmarks.common import provenance, write_results

NAV = {"none": (), "filter": ("scan_filter",), "filter+matcher": ("scan_filter", "scan_matcher")}
CAMERA = {
    "none": (),
    "blobs": ("visible_blobs", "infrared_blobs"),
    "blobs+fusion": ("visible_blobs", "infrared_blobs", "blob_fusion"),
    "all": ("visible_blobs", "infrared_blobs", "blob_fusion", "bayes_inference", "target_map"),
}
FRONT = ("scan_filter", "scan_matcher", "odom_filter", *CAMERA["all"])


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="virtual seconds per placement")
    ap.add_argument("--out", type=Path, default=study.ROOT / "bench/results/lifetime-floor.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    net = study.network_for("app")
    doc = study.APP_FILE.read_text(encoding="utf-8")
    alg1 = study.placement_for("algorithm1-kept", doc, net)
    assert alg1 is not None
    off = "N2"  # a front-end vertex off the leader goes to its neighbour
    rows = []
    with tempfile.TemporaryDirectory(prefix="mso-floor-") as tmp:
        runs = [("algorithm1-kept", alg1)]
        for nav, odom, cam in itertools.product(NAV, (False, True), CAMERA):
            on = {*NAV[nav], *CAMERA[cam], *(("odom_filter",) if odom else ())}
            p = dict(alg1)
            for v in FRONT:
                p[v] = study.LEADER if v in on else (alg1[v] if alg1[v] != study.LEADER else off)
            runs.append((f"nav {nav}, odom filter {'on' if odom else 'off'}, camera {cam}", p))
        for name, p in runs:
            db = Path(tmp) / f"{len(rows)}.sqlite"
            r = study.run(
                name, args.seconds, db, accounting="app", until_leader_dies=False, placement=p
            )
            cpu, radio = r["average_cpu_radio_w"][study.LEADER]
            on_leader = sorted(v for v in FRONT if p[v] == study.LEADER)
            rows.append({"placement": name, "leader_w": r["average_drain_w"][study.LEADER],
                         "leader_cpu_w": cpu, "leader_radio_w": radio,
                         "on_leader": on_leader})  # fmt: skip
            print(f"{name}: leader {1e3 * rows[-1]['leader_w']:.2f} mW", flush=True)
    best = min(rows[1:], key=lambda r: r["leader_w"])
    bound = rows[0]["leader_w"] / best["leader_w"]
    table = "\n".join(
        [
            "| leader-side placement | leader draw (mW) | of which CPU / radio (mW) |",
            "|---|---:|---:|",
            *(
                f"| {r['placement']} | {1e3 * r['leader_w']:.2f} | "
                f"{1e3 * r['leader_cpu_w']:.2f} / {1e3 * r['leader_radio_w']:.2f} |"
                for r in sorted(rows, key=lambda r: r["leader_w"])
            ),
            "",
            f"Lowest: {best['placement']}, {1e3 * best['leader_w']:.2f} mW; Algorithm 1 kept: "
            f"{1e3 * rows[0]['leader_w']:.2f} mW. No static placement makes the leader last more "
            f"than **{bound:.2f}×** as long as under Algorithm 1's.",
            "",
        ]
    )
    result = {"seconds_per_placement": args.seconds, "rows": rows, "bound": bound,
              "seconds": time.perf_counter() - t0, **provenance()}  # fmt: skip
    write_results(args.out, result, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
