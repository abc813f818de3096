"""Every bad input refused: a table of malformed app files, scenario files, node configs and
command-line arguments. Each case runs the real ``mso`` command in a child process and must end
with exit code 2 and one specific line on stderr (file, line and field where there is one).

Time and memory are resource limits on the child, not timed assertions: the kernel stops it past
2 s of CPU (``RLIMIT_CPU``), and its peak RSS, read with ``wait4``, must stay under 200 MB. The
children are forked from one process that has imported ``mso.cli`` (``ZYGOTE``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from waits import listening

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"
APP = str(EXAMPLES / "convoy.yaml")
SCEN = str(EXAMPLES / "convoy-line.yaml")
CPU_S = 2
RSS_LIMIT_KB = 200 * 1024

GOOD_APP = "name: x\nvertices:\n  A: {pinned: N1}\n  B: {}\nedges:\n  - [A, B]\n"
GOOD_SCEN = "name: s\nnodes:\n  N1: {}\n  N2: {}\nlinks:\n  - [N1, N2]\n"
LAUGHS = "".join(
    f"{c}: &{c} [" + ", ".join([f"*{p}"] * 9 if p else ['"lol"'] * 9) + "]\n"
    for p, c in zip(["", *"abcdefg"], "abcdefgh", strict=True)
)
ALIASES = "a: &a 1\nb: [" + ", ".join(["*a"] * 300) + "]\n"


@dataclass
class Case:
    id: str
    args: list[str]  # {f} is the written file
    expected: str  # a substring of the one error line
    text: str | bytes | None = None  # the file's content, written as {f}


def app(id: str, text: str | bytes, expected: str, *extra: str) -> Case:
    return Case(id, ["validate", "{f}", *extra], expected, text)


def scen(id: str, text: str, expected: str) -> Case:
    return Case(id, ["plan", APP, "--scenario", "{f}"], expected, text)


def cfg(id: str, text: str, expected: str) -> Case:
    return Case(id, ["node", "--config", "{f}"], expected, text)


def vertex(attrs: str) -> str:
    return f"name: x\nvertices:\n  A: {{{attrs}}}\n"


CASES = [
    # -- app files --------------------------------------------------------------------------
    app("deep-flow-nesting", "name: x\nvertices: " + "[" * 50_000, "f.yaml:2: nested deeper"),
    app("deep-mapping", "name: x\nvertices: " + "{a: " * 100, "f.yaml:2: nested deeper than 64"),
    app("billion-laughs", LAUGHS, "f.yaml:1: aliases expand to more than"),
    app("too-many-aliases", ALIASES, "f.yaml:2: more than 256 aliases"),
    Case("dev-zero", ["validate", "/dev/zero"], "/dev/zero: not a regular file"),
    Case("a-directory", ["chains", "/tmp"], "is a directory"),
    Case("missing-file", ["validate", "/nonexistent/app.yaml"], "cannot read file"),
    app("over-4-MiB", "name: x\n" + "#" * (5 << 20) + "\n", "f.yaml: file is larger than 4 MiB"),
    app(
        "too-many-vertices",
        "name: x\nvertices:\n" + "".join(f"  v{i}: {{}}\n" for i in range(5001)),
        "f.yaml:2: vertices: more than 5,000 vertices",
    ),
    app("not-utf8", b"name: \xff\xfe\n", "f.yaml: file is not UTF-8 text"),
    app("unclosed-bracket", "name: x\nvertices: [1, 2\n", "f.yaml:2: malformed YAML"),
    app("tab-indent", "name: x\nvertices:\n\tA: {}\n", "f.yaml:3: malformed YAML"),
    app("top-level-list", "- a\n- b\n", "f.yaml:1: expected a mapping with 'name'"),
    app("empty-file", "", "f.yaml: expected a mapping with 'name'"),
    app("no-name", "vertices: {A: {}}\n", "name: expected a non-empty string"),
    app("name-number", "name: 5\nvertices: {A: {}}\n", "f.yaml:1: name: expected a non-empty"),
    app("no-vertices", "name: x\nvertices: {}\n", "f.yaml:2: vertices: expected a non-empty"),
    app("vertices-list", "name: x\nvertices: [A, B]\n", "f.yaml:2: vertices: expected"),
    app("vertex-scalar", "name: x\nvertices:\n  A: 5\n", "f.yaml:3: vertices.A: expected a map"),
    app("unknown-attr", vertex("colour: red"), "f.yaml:3: vertices.A.colour: unknown attribute"),
    app("unknown-top-attr", GOOD_APP + "owner: me\n", "f.yaml:7: owner: unknown attribute"),
    app("cost-negative", vertex("cost: -1"), "f.yaml:3: vertices.A.cost: expected a non-negative"),
    app("cost-1e308", vertex("cost: 1.0e+308"), "vertices.A.cost: expected a non-negative number"),
    app("cost-nan", vertex("cost: .nan"), "f.yaml:3: vertices.A.cost: expected"),
    app("cost-inf", vertex("cost: .inf"), "f.yaml:3: vertices.A.cost: expected"),
    app("cost-string", vertex("cost: lots"), "f.yaml:3: vertices.A.cost: expected"),
    app("rate-zero", vertex("rate: 0"), "f.yaml:3: vertices.A.rate: expected a positive"),
    app("rate-nan", vertex("rate: .nan"), "f.yaml:3: vertices.A.rate: expected a positive"),
    app("pinned-number", vertex("pinned: 5"), "f.yaml:3: vertices.A.pinned: expected a node id"),
    app(
        "edge-size-1e29",
        "name: x\nvertices:\n  A: {}\n  B: {}\nedges:\n  - {from: A, to: B, size: 1"
        + "0" * 29
        + "}\n",
        "f.yaml:6: edges[0].size: expected a non-negative integer byte count up to 16777216",
    ),
    app(
        "edge-size-past-a-frame",
        "name: x\nvertices:\n  A: {}\n  B: {}\nedges:\n  - {from: A, to: B, size: 16777217}\n",
        "f.yaml:6: edges[0].size: expected a non-negative integer byte count up to 16777216",
    ),
    app("params-list", vertex("params: [1]"), "f.yaml:3: vertices.A.params: expected a mapping"),
    app("code-not-a-path", vertex("code: 'rm -rf /'"), "vertices.A.code: expected an import path"),
    app("code-missing-module", vertex("code: 'no_such_mod:X'"), "no module named 'no_such_mod'"),
    app("edge-unknown", GOOD_APP.replace("[A, B]", "[A, Z]"), "f.yaml:6: edges[0]: unknown vertex"),
    app("edge-triple", GOOD_APP.replace("[A, B]", "[A, B, A]"), "f.yaml:6: edges[0]: expected"),
    app("edges-mapping", "name: x\nvertices: {A: {}}\nedges: {A: B}\n", "f.yaml:3: edges:"),
    app(
        "edge-missing-to",
        GOOD_APP.replace("[A, B]", "{from: A}"),
        "f.yaml:6: edges[0].to: expected a vertex id",
    ),
    app(
        "edge-unknown-attr",
        GOOD_APP.replace("[A, B]", "{from: A, to: B, via: C}"),
        "f.yaml:6: edges[0].via: unknown attribute",
    ),
    app("duplicate-key", "name: x\nname: y\nvertices: {A: {}}\n", "f.yaml:2: name: duplicate key"),
    app("boolean-key", "name: x\nvertices:\n  on: {}\n", "f.yaml:3: key 'on' reads as a boolean"),
    app("slo-negative", GOOD_APP + "slo_ms: -5\n", "f.yaml:7: slo_ms: expected a positive"),
    app("policy-number", GOOD_APP + "policy: 5\n", "f.yaml:7: policy: expected a policy name"),
    app(
        "policy-both",
        GOOD_APP + "policy: {name: a, code: 'b:c'}\n",
        "f.yaml:7: policy: expected exactly one of 'name' or 'code'",
    ),
    app(
        "format-bad",
        GOOD_APP.replace("[A, B]", "{from: A, to: B, format: 'x y'}"),
        "edges[0].format: expected an import path",
    ),
    Case(
        "cost-1e308-optimal-planner",
        ["plan", "{f}", "--scenario", SCEN, "--planner", "optimal"],
        "f.yaml:3: vertices.A.cost: expected a non-negative number up to",
        vertex("cost: 1.0e+308, pinned: N1"),
    ),
    # -- scenario files ---------------------------------------------------------------------
    scen("scen-no-nodes", "name: s\n", "f.yaml"),
    scen("scen-cpu-zero", GOOD_SCEN.replace("N2: {}", "N2: {cpu: 0}"), "f.yaml:4: nodes.N2.cpu:"),
    scen("scen-cpu-nan", GOOD_SCEN.replace("N2: {}", "N2: {cpu: .nan}"), "f.yaml:4: nodes.N2.cpu"),
    scen(
        "scen-cpu-huge",
        GOOD_SCEN.replace("N2: {}", "N2: {cpu: 1.0e+300}"),
        "f.yaml:4: nodes.N2.cpu: expected a number <= 1e+12",
    ),
    scen(
        "scen-unknown-link",
        GOOD_SCEN.replace("[N1, N2]", "[N1, N9]"),
        "f.yaml:6: links[0]: unknown node 'N9'",
    ),
    scen(
        "scen-unknown-attr",
        GOOD_SCEN.replace("N2: {}", "N2: {colour: red}"),
        "f.yaml:4: nodes.N2.colour: unknown attribute",
    ),
    scen("scen-deep", "nodes: " + "[" * 10_000, "f.yaml:1: nested deeper than 64"),
    scen("scen-laughs", LAUGHS, "f.yaml:1: aliases expand"),
    Case("scen-dev-zero", ["plan", APP, "--scenario", "/dev/zero"], "/dev/zero: not a regular"),
    # -- node configuration files -----------------------------------------------------------
    cfg("cfg-unknown", "id: N1\nlisten: 127.0.0.1:1\ncolour: red\n", "f.yaml:3: colour: unknown"),
    cfg("cfg-cpu-nan", "id: N1\ncpu: .nan\n", "f.yaml:2: cpu: expected a number > 0"),
    cfg("cfg-cpu-negative", "id: N1\ncpu: -1\n", "f.yaml:2: cpu: expected a number > 0"),
    cfg("cfg-power-negative", "id: N1\npower: {idle_w: -1}\n", "f.yaml:2: power: expected"),
    cfg("cfg-peers-list", "id: N1\npeers: [a, b]\n", "f.yaml:2: peers: expected a mapping"),
    cfg("cfg-manage-string", "id: N1\nmanage: maybe\n", "f.yaml:2: manage: expected true or"),
    cfg("cfg-id-number", "id: 5\n", "f.yaml:1: id: expected a string"),
    cfg("cfg-port-range", "id: N1\nlisten: 127.0.0.1:99999\n", "port in 0..65535"),
    cfg("cfg-not-mapping", "- id\n", "f.yaml:1: expected a mapping"),
    cfg(
        "cfg-allow-code",
        "id: N1\nallow_code: os\n",
        "f.yaml:2: allow_code: expected a list of strings",
    ),
    cfg("cfg-deep", "id: " + "[" * 1000, "f.yaml:1: nested deeper"),
    # -- command-line arguments -------------------------------------------------------------
    Case("listen-port-high", ["node", "--id", "N1", "--listen", "127.0.0.1:99999"], "0..65535"),
    Case("listen-port-negative", ["node", "--id", "N1", "--listen", "127.0.0.1:-1"], "0..65535"),
    Case("listen-port-word", ["node", "--id", "N1", "--listen", "127.0.0.1:http"], "0..65535"),
    Case("cpu-nan", ["node", "--id", "N1", "--cpu", "nan"], "--cpu': expected a finite number > 0"),
    Case("cpu-negative", ["node", "--id", "N1", "--cpu", "-1"], "--cpu': expected a finite"),
    Case("power-negative", ["node", "--id", "N1", "--power", "-1,1,1,1"], "four numbers >= 0"),
    Case("power-short", ["node", "--id", "N1", "--power", "1,2"], "four numbers >= 0"),
    Case("power-nan", ["node", "--id", "N1", "--power", "nan,1,1,1"], "four numbers >= 0"),
    Case("battery-zero", ["node", "--id", "N1", "--battery-wh", "0"], "--battery-wh': expected"),
    Case("heartbeat-nan", ["node", "--id", "N1", "--heartbeat", "nan"], "--heartbeat': expected"),
    Case("peer-port", ["node", "--id", "N1", "--peer", "N2=127.0.0.1:70000"], "0..65535"),
    Case("peer-shape", ["node", "--id", "N1", "--peer", "N2"], "--peer: expected NODE=HOST:PORT"),
    Case("node-no-id", ["node"], "needs an id"),
    Case(
        "listen-beyond-loopback-dev-key", ["node", "--id", "N1", "--listen", "0.0.0.0:0"], "beyond"
    ),
    Case("empty-key", ["node", "--id", "N1", "--key", ""], "empty overlay key is refused"),
    Case("operator-key-bad", ["node", "--id", "N1", "--operator-key", "nope"], "--operator-key"),
    Case(
        "sign-key-bad", ["undeploy", "x", "--via", "127.0.0.1:1", "--sign", "/dev/null"], "--sign"
    ),
    Case(
        "client-key-bad",
        ["status", "--via", "127.0.0.1:1", "--client-key", "/dev/null"],
        "--client-key",
    ),
    Case("allow-code-shape", ["node", "--id", "N1", "--allow-code", "os; rm"], "module name"),
    Case("emulate-duration-nan", ["emulate", SCEN, "--duration", "nan"], "--duration': expected"),
    Case("emulate-convergence", ["emulate", SCEN, "--convergence", "-1"], "--convergence'"),
    Case("simulate-duration", ["simulate", SCEN, "--app", APP, "--duration", "-5"], "--duration'"),
    Case("simulate-conv-inf", ["simulate", SCEN, "--app", APP, "--convergence", "inf"], "finite"),
    Case("demo-duration-nan", ["demo", "--duration", "nan"], "--duration': expected a finite"),
    Case("deploy-via-port", ["deploy", APP, "--via", "127.0.0.1:99999"], "0..65535"),
    Case("status-via-word", ["status", "--via", "127.0.0.1:abc"], "0..65535"),
    Case("planner-unknown", ["plan", APP, "--scenario", SCEN, "--planner", "x"], "'x' is not one"),
    Case("relocate-both", ["relocate", "A", "--upstream", "--to", "N2"], "give exactly one of"),
    Case("remap-nothing", ["remap"], "name a chain"),
    Case("unknown-option", ["validate", APP, "--colour"], "No such option"),
    Case("bench-runs-zero", ["bench", "table1", "--runs", "0"], "--runs"),
]


# A process with ``mso.cli`` (and what its commands load) imported that forks one child per
# case: the child is the real ``mso`` command (its ``main`` on the case's arguments, with the
# limits below), without paying Python's start and mso's imports again for each of the table's
# hundred cases (that was a tenth of the suite's CPU). It reports each child's pid, then its
# exit code, peak RSS and CPU.
ZYGOTE = r"""
import json, os, resource, sys
import mso.cli, mso.model.appfile, mso.planning.baselines, mso.scenario  # what commands load
for line in sys.stdin:
    req = json.loads(line)
    pid = os.fork()
    if pid == 0:
        code = 70
        try:
            os.chdir(req["cwd"])
            null = os.open(os.devnull, os.O_RDWR)
            err = os.open(req["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            os.dup2(null, 0); os.dup2(null, 1); os.dup2(err, 2)
            sys.stdin = open(0, closefd=False)
            resource.setrlimit(resource.RLIMIT_CPU, (req["cpu_s"], req["cpu_s"] + 1))
            resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))  # a safety net only
            sys.argv = ["mso", *req["args"]]
            try:
                mso.cli.main()
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        finally:
            sys.stdout.flush(); sys.stderr.flush()
            os._exit(code)
    print(pid, flush=True)
    _, status, usage = os.wait4(pid, 0)
    print(json.dumps([os.waitstatus_to_exitcode(status), usage.ru_maxrss, usage.ru_utime]),
          flush=True)
"""


class Zygote:
    """The forking process above, started once per test process."""

    def __init__(self) -> None:
        env = {k: v for k, v in os.environ.items() if k != "MSO_KEY"}
        env["OPENBLAS_NUM_THREADS"] = "1"
        self.proc = subprocess.Popen(
            [sys.executable, "-c", ZYGOTE], env=env, text=True,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        )  # fmt: skip
        self.lock = threading.Lock()

    def run(self, args: list[str], cwd: Path) -> tuple[int, str, int, float]:
        """Run ``mso args`` under a CPU limit; (exit code, stderr, peak RSS in KB, CPU s)."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        err = cwd / "stderr"
        req = {"args": args, "cwd": str(cwd), "stderr": str(err), "cpu_s": CPU_S}
        with self.lock:
            self.proc.stdin.write(json.dumps(req) + "\n")
            self.proc.stdin.flush()
            pid = int(self.proc.stdout.readline())
            # a child blocked without using CPU (it should never be) is stopped after 30 s
            watchdog = threading.Timer(30.0, os.kill, (pid, signal.SIGKILL))
            watchdog.start()
            try:
                code, rss_kb, cpu_s = json.loads(self.proc.stdout.readline())
            finally:
                watchdog.cancel()
        return code, err.read_text(errors="replace"), rss_kb, cpu_s

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        self.proc.wait(10)


_zygote: Zygote | None = None


def run_limited(args: list[str], cwd: Path) -> tuple[int, str, int, float]:
    """Run ``mso args`` in a child under a CPU limit; (exit code, stderr, peak RSS in KB, CPU s)."""
    global _zygote
    if _zygote is None or _zygote.proc.poll() is not None:
        _zygote = Zygote()
    return _zygote.run(args, cwd)


@pytest.fixture(scope="module", autouse=True)
def _zygote_stops() -> Iterator[None]:
    yield
    if _zygote is not None:
        _zygote.close()


def test_the_table_is_big_enough() -> None:
    assert len(CASES) >= 60
    assert len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_one_line_and_exit_2(case: Case, tmp_path: Path) -> None:
    f = tmp_path / "f.yaml"
    if case.text is not None:
        f.write_bytes(case.text.encode() if isinstance(case.text, str) else case.text)
    args = [a.replace("{f}", str(f)) for a in case.args]
    code, err, rss_kb, _ = run_limited(args, tmp_path)
    assert code == 2, f"exit {code} (-{CPU_S} s CPU limit is SIGXCPU): {err}"
    assert "Traceback" not in err
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert err.startswith("error: ")
    assert case.expected in err
    assert rss_kb < RSS_LIMIT_KB, f"peak RSS {rss_kb} KB"


@pytest.mark.slow
def test_live_node_wrong_key_and_unknown_app(tmp_path: Path) -> None:
    """Against a running node: a wrong key fails at once with what is wrong, and undeploying an
    app that is not running is an error, not a success."""
    env = {**os.environ, "MSO_KEY": "right"}
    log = tmp_path / "node.log"
    with log.open("wb") as out:
        node = subprocess.Popen(
            [sys.executable, "-m", "mso", "node", "--id", "N1", "--listen", "127.0.0.1:0"],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        addr = f"127.0.0.1:{listening(node, log)}"
        code, err, _, _ = run_limited(["status", "--via", addr, "--key", "wrong"], tmp_path)
        assert code == 2 and err.count("\n") == 1
        assert "wrong overlay key" in err
        code, err, _, _ = run_limited(
            ["undeploy", "ghost", "--via", addr, "--key", "right"], tmp_path
        )
        assert code == 2 and "no running app named 'ghost'" in err
    finally:
        node.terminate()
        node.wait(10)
