"""The dashboard checks ``Host`` and ``Origin`` on every address it listens on: a page that
rebinds its own name to a loopback address other than 127.0.0.1 (127.0.0.2, ::1, a listen
name) used to pass, and relocated a vertex with the operator's signing key."""

from __future__ import annotations

import asyncio
import http.client
import json
import socket

import pytest

from mso.dashboard.server import Dashboard


def ask(
    host: str, port: int, method: str, path: str, headers: dict[str, str], body: bytes = b""
) -> tuple[int, str]:
    conn = http.client.HTTPConnection(host, port, timeout=10)
    try:
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        for k, v in headers.items():
            conn.putheader(k, v)
        conn.putheader("Content-Length", str(len(body)))
        conn.endheaders(body)
        reply = conn.getresponse()
        return reply.status, reply.read().decode()
    finally:
        conn.close()


def _has_ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


LISTENS = ["127.0.0.2", "127.0.0.1", "localhost"] + (["::1"] if _has_ipv6_loopback() else [])


@pytest.mark.parametrize("listen", LISTENS)
def test_host_and_origin_are_checked_on_every_loopback_address(listen: str) -> None:
    async def run() -> None:
        # a node that is not there: the checks come before anything is asked of it
        board = Dashboard(["127.0.0.1:9"], "k", listen=f"{listen}:0")
        await board.start()
        try:
            port = board.port
            connect = listen if listen != "localhost" else "127.0.0.1"
            own = f"[{listen}]:{port}" if ":" in listen else f"{listen}:{port}"
            json_ct = {"Content-Type": "application/json"}
            body = json.dumps({"app": "a", "vertex": "v", "target": "N2"}).encode()

            def call(method: str, path: str, headers: dict[str, str]) -> tuple[int, str]:
                return ask(connect, port, method, path, headers, body if method == "POST" else b"")

            for good in (
                own,
                f"localhost:{port}",
                f"[::1]:{port}" if listen != "localhost" else own,
            ):
                code, text = await asyncio.to_thread(call, "GET", "/api/view", {"Host": good})
                assert code == 200, (good, text)
            refused_hosts = [
                f"attacker.example:{port}",  # a rebound name
                f"{listen}.attacker.example:{port}",
                f"10.1.2.3:{port}",  # an address this dashboard does not listen on
                "2130706433",  # not an address literal a browser sends
                "",
            ]
            for bad in refused_hosts:
                for method, path in (("GET", "/api/view"), ("GET", "/events"),
                                     ("POST", "/api/relocate"), ("GET", "/")):  # fmt: skip
                    headers = {"Host": bad, **json_ct} if bad else dict(json_ct)
                    code, text = await asyncio.to_thread(call, method, path, headers)
                    assert code == 403 and "Host" in text, (bad, method, path, code, text)
            for origin in ("http://attacker.example", f"http://attacker.example:{port}", "null",
                           f"https://{own}"):  # fmt: skip
                for method, path in (("POST", "/api/relocate"), ("POST", "/api/remap"),
                                     ("GET", "/api/view")):  # fmt: skip
                    headers = {"Host": own, "Origin": origin, **json_ct}
                    code, text = await asyncio.to_thread(call, method, path, headers)
                    assert code == 403 and "Origin" in text, (origin, method, code, text)
            # its own page's request passes the checks (and reaches the missing node: 502)
            headers = {"Host": own, "Origin": f"http://{own}", **json_ct}
            code, text = await asyncio.to_thread(call, "POST", "/api/relocate", headers)
            assert code == 502 and "cannot reach node" in text, text
        finally:
            await board.stop()

    asyncio.run(asyncio.wait_for(run(), 60))
