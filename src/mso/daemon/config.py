"""A node's settings: the flags given, over its ``--config`` file, over the defaults, checked
in one place so that a mistake is reported in one line before anything listens."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mso.errors import MsoError

if TYPE_CHECKING:
    from mso.management.guard import RuleSettings
    from mso.model.network import PowerModel
    from mso.net.base import Neighbour
    from mso.protocol.authority import Authority
    from mso.protocol.identity import Identity

DEFAULT_LISTEN = "127.0.0.1:7000"
DEV_KEY_WARNING = (
    "warning: using the built-in development key: anyone who has mso can join this overlay; "
    "give --key or set $MSO_KEY"
)
NODE_CONFIG_KEYS = {
    "id",
    "listen",
    "cpu",
    "key",
    "peers",
    "battery_wh",
    "link_mbps",
    "power",
    "policy",
    "manage",
    "allow_code",
    "operator_keys",
    "key_file",
    "encrypt",
    "routes",
    "energy",
    "heartbeat",
    "dead_after",
    "metrics",
    "insecure",
    "verbose",
    "rules",
    "capabilities",
    "state_dir",
    "identity",
    "revoked_nodes",
    "strict_moves",
}


@dataclass
class NodeFlags:
    """What a command line gave (None, or empty: not given, so the config file or the default
    decides)."""

    config_file: Path | None = None
    node_id: str | None = None
    listen: str | None = None
    cpu: float | None = None
    battery_wh: float | None = None
    link_mbps: tuple[str, ...] = ()  # RATE or PEER=RATE, each --link-mbps
    # NAME or NAME=AMOUNT, each --capability (§3.3: camera, gpu, mem_mb=4096)
    capabilities: tuple[str, ...] = ()
    power: PowerModel | None = None  # parsed by the front end (its own error message)
    peers: tuple[str, ...] = ()
    energy: str | None = None
    routes_from: str | None = None
    policy: str | None = None
    manage: bool | None = None
    heartbeat_s: float | None = None
    dead_after_s: float | None = None
    metrics: str | None = None
    allow_code: tuple[str, ...] = ()
    operator_keys: tuple[str, ...] = ()
    key_file: Path | None = None
    encrypt: bool | None = None
    insecure: bool = False
    key: str | None = None
    verbose: bool = False
    rules: tuple[str, ...] = ()  # NAME=VALUE, each a RuleSettings field
    state_dir: Path | None = None
    identity: Path | None = None  # this node's key file (its certificate beside it, .cert)
    revoked_nodes: tuple[str, ...] = ()  # node key ids the operator withdrew
    strict_moves: bool | None = None  # a chain end's remap needs an operator's order


@dataclass
class NodeSettings:
    """Everything the assembly needs, checked."""

    node_id: str
    listen: str
    host: str
    port: int
    cpu: float
    power: PowerModel
    heartbeat_s: float
    dead_after_s: float
    key: str | None = None
    key_file: Path | None = None
    dev_key: bool = False  # the built-in development key: said on stderr at start
    encrypt: bool = False
    authority: Authority | None = None
    battery_wh: float | None = None
    # the configured rates of its links (Mb/s) where the routing view knows none, by peer
    # ("*": every other link): probes carry them
    link_mbps: dict[str, float] = field(default_factory=dict)
    capabilities: dict[str, float] = field(default_factory=dict)
    policy: str | None = None
    manage: bool = True
    peers: dict[str, Neighbour] = field(default_factory=dict)
    metrics_at: tuple[str, int] | None = None
    routes_from: str = "auto"
    energy: str = "auto"
    verbose: bool = False
    rules: RuleSettings | None = None  # None: the defaults (docs/policies.md)
    state_dir: Path | None = None  # the durable spill store's (None: in memory)
    identity: Identity | None = None  # this node's own key and certificate


def settle(flags: NodeFlags) -> NodeSettings:
    """The flags over the config file over the defaults, every value checked; restricts this
    process's code imports (before anything of an app is loaded)."""
    from mso.client import parse_address
    from mso.model.network import PowerModel
    from mso.protocol.procedures.membership.liveness import DEAD_AFTER_S, HEARTBEAT_S, check_timing

    cfg = node_config(flags.config_file) if flags.config_file is not None else {}
    heartbeat_s = flags.heartbeat_s if flags.heartbeat_s is not None else cfg.get("heartbeat")
    heartbeat_s = HEARTBEAT_S if heartbeat_s is None else heartbeat_s
    dead_after_s = flags.dead_after_s if flags.dead_after_s is not None else cfg.get("dead_after")
    dead_after_s = DEAD_AFTER_S if dead_after_s is None else dead_after_s
    if why := check_timing(heartbeat_s, dead_after_s):
        raise MsoError(why)
    node_id = flags.node_id or cfg.get("id")
    if not node_id:
        raise MsoError("a node needs an id: --id N1, or 'id:' in its --config file")
    all_peers = tuple(f"{n}={a}" for n, a in cfg.get("peers", {}).items()) + flags.peers
    power = flags.power or PowerModel(**cfg.get("power", {}))
    set_code_allowlist(flags.allow_code or tuple(cfg.get("allow_code", ())))
    key = flags.key if flags.key is not None else cfg.get("key")
    key_file = flags.key_file or (Path(cfg["key_file"]) if "key_file" in cfg else None)
    if key_file is not None:
        key = read_keys(key_file)[0]  # checked now; re-read on SIGHUP
    encrypt = bool(cfg.get("encrypt", False)) if flags.encrypt is None else flags.encrypt
    authority = node_authority(flags.operator_keys or tuple(cfg.get("operator_keys", ())))
    revoked = flags.revoked_nodes or tuple(cfg.get("revoked_nodes", ()))
    authority.revoked_nodes = frozenset(revoked)
    strict = flags.strict_moves if flags.strict_moves is not None else cfg.get("strict_moves")
    authority.strict_moves = bool(strict)
    if authority.strict_moves and not authority.signed:
        raise MsoError("--strict-moves needs --operator-key: a move's order is an operator's")
    identity = node_identity(flags.identity or cfg.get("identity"), node_id, authority)
    listen = flags.listen or cfg.get("listen", DEFAULT_LISTEN)
    dev_key = check_key(key, listen, flags.insecure or bool(cfg.get("insecure", False)))
    battery = flags.battery_wh if flags.battery_wh is not None else cfg.get("battery_wh")
    if battery is not None and battery <= 0:
        raise MsoError(f"--battery-wh: expected a number > 0, got {battery:g}")
    cpu = float(flags.cpu if flags.cpu is not None else cfg.get("cpu", 1.0))
    link_mbps = link_rates(flags.link_mbps, cfg.get("link_mbps"))
    capabilities = node_capabilities(flags.capabilities, cfg.get("capabilities"))
    host, port = parse_address(listen)
    metrics_at = None
    metrics = flags.metrics if flags.metrics is not None else cfg.get("metrics")
    if metrics is not None:
        metrics_at = parse_address(metrics, default_port=-1)
        if not 0 <= metrics_at[1] < 65536:
            raise MsoError(f"--metrics: expected HOST:PORT, got {metrics!r}")
    if cpu <= 0:
        raise MsoError(f"--cpu: expected a number > 0, got {cpu:g}")
    peers = static_peers(all_peers)
    energy = flags.energy or cfg.get("energy", "auto")
    routes_from = flags.routes_from or cfg.get("routes", "auto")
    check_routes(energy, routes_from, peers, host, port, listen)
    return NodeSettings(
        node_id=node_id,
        listen=listen,
        host=host,
        port=port,
        cpu=cpu,
        power=power,
        heartbeat_s=heartbeat_s,
        dead_after_s=dead_after_s,
        key=key,
        key_file=key_file,
        dev_key=dev_key,
        encrypt=encrypt,
        authority=authority,
        battery_wh=battery,
        link_mbps=link_mbps,
        capabilities=capabilities,
        policy=flags.policy if flags.policy is not None else cfg.get("policy"),
        manage=flags.manage if flags.manage is not None else cfg.get("manage", True),
        peers=peers,
        metrics_at=metrics_at,
        routes_from=routes_from,
        energy=energy,
        verbose=flags.verbose or bool(cfg.get("verbose", False)),
        rules=rule_settings(cfg.get("rules", {}), flags.rules),
        state_dir=flags.state_dir or (Path(cfg["state_dir"]) if "state_dir" in cfg else None),
        identity=identity,
    )


def rule_settings(given: dict[str, Any], flags: tuple[str, ...]) -> RuleSettings | None:
    """The management rules' settings: a config file's ``rules:`` mapping, then each
    ``--rule NAME=VALUE`` over it; None when neither says anything (the defaults)."""
    import dataclasses

    from mso.management.guard import RuleSettings

    names = {f.name: f for f in dataclasses.fields(RuleSettings)}
    values = dict(given)
    for text in flags:
        name, eq, raw = text.partition("=")
        if not eq or name not in names:
            raise MsoError(
                f"--rule: expected NAME=VALUE with NAME one of {', '.join(names)}, got {text!r}"
            )
        values[name] = _rule_value(name, raw, names[name].default)
    if not values:
        return None
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise MsoError(
            f"rules: unknown setting {unknown[0]!r} (expected one of {', '.join(names)})"
        )
    return RuleSettings(**values)  # checks each value, naming the setting


def _rule_value(name: str, raw: str, default: Any) -> Any:
    """``--rule`` text as the type of the setting's default."""
    try:
        if isinstance(default, bool):
            if raw.lower() not in ("true", "false"):
                raise ValueError(raw)
            return raw.lower() == "true"
        return type(default)(raw)
    except ValueError:
        raise MsoError(f"--rule {name}: expected a {type(default).__name__}, got {raw!r}") from None


def static_peers(peers: tuple[str, ...]) -> dict[str, Neighbour]:
    """``NODE=HOST:PORT`` each -> the fixed neighbours of a set-up without a routing daemon."""
    from mso.client import parse_address
    from mso.net.base import Neighbour

    static: dict[str, Neighbour] = {}
    for p in peers:
        name, _, addr = p.partition("=")
        if not name or not addr:
            raise MsoError(f"--peer: expected NODE=HOST:PORT, got {p!r}")
        phost, pport = parse_address(addr)
        static[name] = Neighbour(phost, pport)
    return static


def check_routes(
    energy: str, routes_from: str, peers: dict[str, Neighbour], host: str, port: int, listen: str
) -> None:
    """Where energy and routes come from (a config file's values are checked here too)."""
    if energy not in ("auto", "model", "interfaces"):
        raise MsoError(f"energy: expected auto, model or interfaces, got {energy!r}")
    if routes_from not in ("auto", "kernel", "emulator"):
        raise MsoError(f"routes: expected auto, kernel or emulator, got {routes_from!r}")
    if routes_from == "kernel" and peers:
        raise MsoError("give either --peer (a fixed set-up) or --routes kernel, not both")
    if routes_from == "kernel" and (port == 0 or host.startswith("127.") or host == "localhost"):
        raise MsoError(
            f"--routes kernel: listen on a routable address and a fixed port "
            f"(e.g. --listen 0.0.0.0:7000), got {listen}"
        )


def node_config(path: Path) -> dict[str, Any]:
    """A node configuration file: any of ``mso node``'s options by name (peers: node id ->
    HOST:PORT; rules: setting -> value), each checked here with its line."""
    from mso.errors import SpecError
    from mso.model.yamlfile import load_yaml_file

    doc = load_yaml_file(path)
    data = doc.data
    if not isinstance(data, dict):
        raise SpecError("expected a mapping with 'id' and 'listen'", file=doc.file, line=1)
    for k, v in data.items():
        line = doc.line((k,))
        if k not in NODE_CONFIG_KEYS:
            allowed = ", ".join(sorted(NODE_CONFIG_KEYS))
            raise SpecError(
                f"unknown attribute {k!r} (expected one of: {allowed})",
                file=doc.file,
                line=line,
                field=str(k),
            )
        if why := _config_value_problem(k, v):
            raise SpecError(why, file=doc.file, line=line, field=k)
    return data


def _rate(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and 0 < v < 1e9


def link_rates(flags: tuple[str, ...], configured: Any) -> dict[str, float]:
    """The configured rates (Mb/s) of this node's links, by peer, ``"*"`` for the rest:
    ``--link-mbps RATE`` / ``--link-mbps PEER=RATE`` options (repeat), else the config file's
    ``link_mbps:`` (a rate, or a mapping of peer to rate). Configured, not measured: probes
    carry them to the planner where the routing view knows no rate."""
    if not flags:
        if configured is None:
            return {}
        if _rate(configured):
            return {"*": float(configured)}
        return {str(p): float(x) for p, x in configured.items()}
    out: dict[str, float] = {}
    for item in flags:
        peer, _, rate = item.rpartition("=")
        try:
            value = float(rate)
        except ValueError:
            value = math.nan
        if not _rate(value) or (not peer and "=" in item):
            raise MsoError(f"--link-mbps: expected RATE or PEER=RATE in Mb/s > 0, got {item!r}")
        out[peer or "*"] = value
    return out


def node_capabilities(flags: tuple[str, ...], configured: Any) -> dict[str, float]:
    """What a node offers (§3.3): ``--capability NAME[=AMOUNT]`` options, else the config
    file's ``capabilities:`` (a list of names or a mapping of name to amount)."""
    from mso.errors import AppError
    from mso.model.capabilities import parse_capabilities

    spec: Any = configured
    if flags:
        spec = {}
        for item in flags:
            name, _, amount = item.partition("=")
            try:
                spec[name] = float(amount) if amount else 1.0
            except ValueError:
                raise MsoError(
                    f"--capability: expected NAME or NAME=AMOUNT, got {item!r}"
                ) from None
    try:
        return parse_capabilities(spec, "capabilities")
    except AppError as exc:
        raise MsoError(f"{'--capability' if flags else 'capabilities'}: {exc.message}") from None


def _config_value_problem(k: str, v: Any) -> str | None:
    """What is wrong with the value ``v`` of attribute ``k`` of a node config file, if anything."""
    if k == "peers" and not (isinstance(v, dict) and all(isinstance(a, str) for a in v.values())):
        return "expected a mapping of node id to HOST:PORT"
    if k == "power" and not (
        isinstance(v, dict)
        and set(v) <= {"idle_w", "cpu_w", "tx_uj_per_byte", "rx_uj_per_byte"}
        and all(
            isinstance(x, int | float) and not isinstance(x, bool) and 0 <= x < 1e12
            for x in v.values()
        )
    ):
        return "expected {idle_w, cpu_w, tx_uj_per_byte, rx_uj_per_byte} as numbers >= 0"
    if k == "link_mbps" and not (
        _rate(v)
        or (isinstance(v, dict) and all(isinstance(p, str) and _rate(x) for p, x in v.items()))
    ):
        return (
            f"expected a rate in Mb/s > 0, or a mapping of peer ('*': the rest) to one, got {v!r}"
        )
    if k in ("cpu", "battery_wh") and not (
        isinstance(v, int | float) and not isinstance(v, bool) and 0 < v < 1e12
    ):
        return f"expected a number > 0, got {v!r}"
    if k in ("heartbeat", "dead_after") and not (
        isinstance(v, int | float) and not isinstance(v, bool) and 0 < v < 1e6
    ):
        return f"expected seconds > 0, got {v!r}"
    if k == "rules" and not (isinstance(v, dict) and all(isinstance(x, str) for x in v)):
        return "expected a mapping of rule setting to value (docs/policies.md), e.g. warmup_s: 5"
    if k in ("manage", "encrypt", "insecure", "verbose", "strict_moves") and not isinstance(
        v, bool
    ):
        return f"expected true or false, got {v!r}"
    if k in ("allow_code", "operator_keys", "revoked_nodes") and not (
        isinstance(v, list) and all(isinstance(x, str) and x for x in v)
    ):
        return "expected a list of strings"
    if k in ("id", "listen", "key", "key_file", "metrics", "state_dir", "identity") and not (
        isinstance(v, str)
    ):
        return f"expected a string, got {v!r}"
    return None


def read_keys(path: Path) -> list[str]:
    """A key file: overlay keys one a line (the first seals), '#' comments."""
    from mso.errors import SpecError
    from mso.model.yamlfile import read_text_file

    keys = [
        line.strip()
        for line in read_text_file(path).splitlines()
        if line.strip() and not line.strip().startswith("#")
    ]
    if not keys:
        raise SpecError("no overlay key in the key file", file=str(path))
    return keys


def node_authority(keys: tuple[str, ...]) -> Authority:
    """The operator keys (and the emulator's, from $MSO_EMULATOR_KEY) this node obeys."""
    from mso.protocol.authority import Authority, KeyError_

    try:
        return Authority.from_env(list(keys))
    except KeyError_ as exc:
        raise MsoError(f"--operator-key: {exc}") from None


def node_identity(path: str | Path | None, node_id: str, authority: Authority) -> Identity | None:
    """This node's identity from its key file (``--identity``): its certificate must name this
    node and be signed by an operator key it was given."""
    if path is None:
        return None
    from mso.protocol.authority import KeyError_
    from mso.protocol.identity import Identity

    try:
        identity = Identity.load(path)
    except KeyError_ as exc:
        raise MsoError(f"--identity: {exc}") from None
    if identity.node != node_id:
        raise MsoError(f"--identity: {path} certifies {identity.node!r}, not {node_id!r}")
    if identity.cert.operator not in authority.operators:
        raise MsoError(f"--identity: {path}.cert is signed by a key not given to --operator-key")
    return identity


def check_key(key: str | None, listen: str, insecure: bool) -> bool:
    """Protected mode: an empty key is an error; the built-in development key is announced,
    and refused on an address beyond loopback unless ``--insecure``."""
    import ipaddress

    from mso.client import DEFAULT_KEY, parse_address

    if key == "":
        raise MsoError("--key: an empty overlay key is refused (give one, or leave --key out)")
    if key is not None and key != DEFAULT_KEY:
        return False
    host, _ = parse_address(listen)
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback and not insecure:
        raise MsoError(
            f"--listen {listen}: refusing to listen beyond loopback with the built-in "
            "development key; give --key or $MSO_KEY (or --insecure for a lab network)"
        )
    return True


def set_code_allowlist(modules: tuple[str, ...]) -> tuple[str, ...]:
    """Restrict this process's imports to ``modules`` (else $MSO_ALLOW_CODE) plus the bundled
    examples, before anything of an app is loaded."""
    from mso.model.imports import DEFAULT_ALLOWED, ImportPathError, allow_code

    if not modules:
        modules = tuple(m for m in os.environ.get("MSO_ALLOW_CODE", "").split(",") if m)
    allowed = (*DEFAULT_ALLOWED, *modules)
    try:
        allow_code(allowed)
    except ImportPathError as exc:
        raise MsoError(f"--allow-code: {exc}") from None
    return allowed
