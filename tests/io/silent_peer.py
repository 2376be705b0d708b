"""A peer that accepts a TCP connection on 127.0.0.1 and never says a word (a device whose
link is up but whose firmware hangs): what every driver's bounded connect is tested against."""

from __future__ import annotations

import asyncio
import contextlib


@contextlib.asynccontextmanager
async def silent_peer():
    """Yields the port of a server that accepts and stays silent; closed on exit."""
    accepted: list[asyncio.StreamWriter] = []

    async def silent(reader, writer):
        accepted.append(writer)

    server = await asyncio.start_server(silent, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        for w in accepted:
            w.close()
        server.close()
        await server.wait_closed()
