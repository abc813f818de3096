"""The Python API to a running overlay: what the CLI does, from a program.

    from mso.api import Overlay

    overlay = Overlay("127.0.1.1:7000", key="...", sign="op.key")   # sign: an operator key
    overlay.deploy("examples/convoy.yaml")
    overlay.relocate("convoy", "scan_matcher", direction="upstream")
    overlay.remap("convoy", chains=[0, 4])          # or everything=True
    print(overlay.status()["N1"]["apps"])

Every call connects to the given node, which may be any node of the overlay. Refusals raise
:class:`mso.errors.MsoError` with the node's reason. ``AsyncOverlay`` is the same for asyncio code.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from mso.client import load_signer, request
from mso.errors import MsoError
from mso.model.app import App
from mso.model.appfile import load_app
from mso.model.yamlfile import read_text_file
from mso.protocol import messages as m


class AsyncOverlay:
    """Asynchronous access to an overlay through one of its nodes."""

    def __init__(
        self,
        address: str,
        *,
        key: str | None = None,
        timeout: float = 30.0,
        sign: str | None = None,
    ) -> None:
        self.address = address
        self.key = key
        self.timeout = timeout
        # an operator key file: commands that change the overlay are signed with it
        self.signer = load_signer(sign)

    async def _call(self, msg: m.Message) -> Any:
        return await request(
            self.address, msg, key=self.key, timeout=self.timeout, signer=self.signer
        )

    async def deploy(self, app_file: str | Path) -> m.DeployReply:
        """Deploy an app file (validated here first, so errors point at its lines)."""
        path = Path(app_file)
        load_app(path)
        reply = await self._call(m.DeployRequest(read_text_file(path), str(path)))
        if not isinstance(reply, m.DeployReply) or not reply.ok:
            raise MsoError(f"deployment failed: {getattr(reply, 'error', reply)}")
        return reply

    async def undeploy(self, app: str | App) -> None:
        await self._call(m.StopApp(app.name if isinstance(app, App) else app))

    async def relocate(
        self, app: str, vertex: str, *, direction: str = "", target: str = ""
    ) -> m.RelocateReply:
        """Move one interior vertex upstream, downstream, or to ``target`` (§3.4.1)."""
        reply = await self._call(m.RelocateRequest(app, vertex, direction, target))
        if not isinstance(reply, m.RelocateReply) or not reply.ok:
            raise MsoError(f"relocation refused: {getattr(reply, 'error', reply)}")
        return reply

    async def remap(
        self, app: str, *, chains: list[int] | None = None, everything: bool = False
    ) -> m.RemapReply:
        """Re-place chains (by index) or all of them, in dependency order (§3.4.2, §3.4.3)."""
        reply = await self._call(m.RemapRequest(app, list(chains or []), everything))
        if not isinstance(reply, m.RemapReply) or not reply.ok:
            raise MsoError(f"remap refused: {getattr(reply, 'error', reply)}")
        return reply

    async def status(self) -> dict[str, Any]:
        """Every reachable node's status, by node id."""
        reply = await self._call(m.StatusRequest(everywhere=True))
        if not isinstance(reply, m.StatusReply):
            raise MsoError(f"unexpected reply {reply!r}")
        return reply.nodes


class Overlay:
    """Blocking access to an overlay through one of its nodes (not for use inside a loop)."""

    def __init__(
        self,
        address: str,
        *,
        key: str | None = None,
        timeout: float = 30.0,
        sign: str | None = None,
    ) -> None:
        self._async = AsyncOverlay(address, key=key, timeout=timeout, sign=sign)

    def deploy(self, app_file: str | Path) -> m.DeployReply:
        return asyncio.run(self._async.deploy(app_file))

    def undeploy(self, app: str | App) -> None:
        asyncio.run(self._async.undeploy(app))

    def relocate(
        self, app: str, vertex: str, *, direction: str = "", target: str = ""
    ) -> m.RelocateReply:
        return asyncio.run(self._async.relocate(app, vertex, direction=direction, target=target))

    def remap(
        self, app: str, *, chains: list[int] | None = None, everything: bool = False
    ) -> m.RemapReply:
        return asyncio.run(self._async.remap(app, chains=chains, everything=everything))

    def status(self) -> dict[str, Any]:
        return asyncio.run(self._async.status())
