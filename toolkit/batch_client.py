"""``crossview batch --scheduler ADDR``: connect to a running Dask scheduler or fail fast, and the
line each finished scene prints.

``distributed.Client`` waits forever for the handshake of an address that is not a scheduler (an
HTTP port such as the dashboard's), retries an unreachable one for its whole timeout, and accepts
a scheduler without workers, on which the batch would then wait forever. Here each case is one
``CrossviewError`` line (exit 2), each within ``REACH_S`` + ``HANDSHAKE_S`` or ``WORKERS_S``.
"""

from __future__ import annotations

import asyncio
import socket
from typing import Any

from toolkit.errors import CrossviewError

REACH_S = 10.0  # TCP connection to the scheduler's host and port
HANDSHAKE_S = 5.0  # Dask handshake and identity reply
WORKERS_S = 10.0  # a scheduler without workers gets this long for one to join
EXAMPLE = "tcp://host:8786"


def connect_scheduler(address: str) -> Any:
    """A ``distributed.Client`` on the scheduler at ``address`` that has at least one worker."""
    from distributed import Client

    where = f"--scheduler {address}"
    _reach(address, where)
    _check_identity(address, where)
    try:
        client = Client(address, timeout=f"{REACH_S}s")
    except (OSError, TimeoutError) as exc:
        raise CrossviewError(f"{where}: cannot connect ({' '.join(str(exc).split())})") from exc
    try:
        client.wait_for_workers(1, timeout=WORKERS_S)
    except TimeoutError as exc:
        client.close()
        raise CrossviewError(f"{where}: the scheduler has no workers (none joined within {WORKERS_S:g} s); "
                             f"start some with: dask worker {address}") from exc
    return client


def _reach(address: str, where: str) -> None:
    """The scheduler's TCP port accepts a connection (skipped for schemes without host and port)."""
    from distributed.comm.addressing import get_address_host_port

    try:
        host, port = get_address_host_port(address)
    except ValueError as exc:
        if "unknown address scheme" in str(exc):
            raise CrossviewError(f"{where}: {exc}; a Dask scheduler address looks like {EXAMPLE}") from exc
        return
    try:
        socket.create_connection((host, port), timeout=REACH_S).close()
    except ConnectionRefusedError as exc:
        raise CrossviewError(f"{where}: connection refused: no scheduler listens on {host}:{port}") from exc
    except TimeoutError as exc:
        raise CrossviewError(f"{where}: no answer from {host}:{port} within {REACH_S:g} s (unreachable)") from exc
    except OSError as exc:
        raise CrossviewError(f"{where}: cannot connect to {host}:{port} ({exc.strerror or exc})") from exc


def _check_identity(address: str, where: str) -> None:
    try:
        identity = asyncio.run(_identity(address))
    except Exception as exc:  # a timeout, a closed connection, frames that are not Dask's
        raise CrossviewError(f"{where}: not a Dask scheduler (no Dask handshake within {HANDSHAKE_S:g} s; "
                             f"an HTTP port such as the dashboard's?); give the scheduler's address, "
                             f"e.g. {EXAMPLE}") from exc
    kind = identity.get("type") if isinstance(identity, dict) else None
    if kind != "Scheduler":
        raise CrossviewError(f"{where}: not a Dask scheduler (it answers as {kind or 'something else'}); "
                             f"give the scheduler's address, e.g. {EXAMPLE}")


async def _identity(address: str) -> Any:
    from distributed.comm import connect

    comm = await asyncio.wait_for(connect(address, timeout=HANDSHAKE_S), HANDSHAKE_S)
    try:
        await asyncio.wait_for(comm.write({"op": "identity", "reply": True}), HANDSHAKE_S)
        return await asyncio.wait_for(comm.read(), HANDSHAKE_S)
    finally:
        comm.abort()


def finished_line(row: dict[str, Any]) -> str:
    """``scene: status, confidence C, S s`` (and the error of a scene that did not finish)."""
    parts = [f"{row['scene']}: {row['status']}"]
    if row.get("confidence") is not None:
        parts.append(f"confidence {row['confidence']:.2f}")
    parts.append(f"{row.get('seconds', 0.0):.1f} s")
    line = ", ".join(parts)
    return f"{line}: {row['error']}" if row.get("error") else line
