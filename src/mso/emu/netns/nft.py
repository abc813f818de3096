"""nftables commands run in-process, inside one network namespace.

libnftables (the library under the ``nft`` command) is called through ctypes on a thread that
lives in the namespace: a link change is then one call, effective when it returns (about 0.6 ms
here; forking ``nft`` per change costs 6-16 ms, and a persistent ``nft -i`` pipe answers
asynchronously and leaked a packet in the measurements of the testbed notes). Where the
library cannot be loaded, each batch forks ``ip netns exec NS nft -f -`` instead.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import subprocess
from typing import Any

from mso.errors import MsoError
from mso.net.netns import worker


class Nft:
    """Run nft command batches in namespace ``netns``."""

    def __init__(self, netns: str) -> None:
        self.netns = netns
        self.calls = 0
        self._lib: Any = None
        self._ctx: Any = None
        self._worker = worker(netns)
        name = ctypes.util.find_library("nftables") or "libnftables.so.1"
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            return  # fork nft per batch instead
        lib.nft_ctx_new.restype = ctypes.c_void_p
        lib.nft_ctx_new.argtypes = [ctypes.c_uint32]
        lib.nft_ctx_free.argtypes = [ctypes.c_void_p]
        lib.nft_run_cmd_from_buffer.argtypes = [ctypes.c_void_p, ctypes.c_char_p]
        lib.nft_run_cmd_from_buffer.restype = ctypes.c_int
        lib.nft_ctx_buffer_error.argtypes = [ctypes.c_void_p]
        lib.nft_ctx_buffer_output.argtypes = [ctypes.c_void_p]
        lib.nft_ctx_get_error_buffer.argtypes = [ctypes.c_void_p]
        lib.nft_ctx_get_error_buffer.restype = ctypes.c_char_p
        lib.nft_ctx_get_output_buffer.argtypes = [ctypes.c_void_p]
        lib.nft_ctx_get_output_buffer.restype = ctypes.c_char_p
        self._lib = lib

        def make() -> Any:
            ctx = lib.nft_ctx_new(0)
            lib.nft_ctx_buffer_error(ctx)
            lib.nft_ctx_buffer_output(ctx)
            return ctx

        self._ctx = self._worker.submit(make).result()

    @property
    def in_process(self) -> bool:
        return self._ctx is not None

    def run(self, commands: str) -> str:
        """Run a batch (one transaction); its output. Raises MsoError with nft's message."""
        self.calls += 1
        if self._ctx is None:
            proc = subprocess.run(
                ["ip", "netns", "exec", self.netns, "nft", "-f", "-"],
                input=commands.encode(),
                capture_output=True,
            )
            if proc.returncode != 0:
                raise MsoError(f"nft in {self.netns}: {proc.stderr.decode().strip()}")
            return proc.stdout.decode()
        lib, ctx = self._lib, self._ctx

        def call() -> tuple[int, bytes, bytes]:
            rc = lib.nft_run_cmd_from_buffer(ctx, commands.encode())
            return (
                rc,
                lib.nft_ctx_get_error_buffer(ctx) or b"",
                lib.nft_ctx_get_output_buffer(ctx) or b"",
            )

        rc, err, out = self._worker.submit(call).result()
        if rc != 0:
            raise MsoError(f"nft in {self.netns}: {err.decode().strip()}")
        return out.decode()

    def close(self) -> None:
        if self._ctx is not None:
            ctx, self._ctx = self._ctx, None
            self._worker.submit(self._lib.nft_ctx_free, ctx).result()
        self._worker.shutdown()
