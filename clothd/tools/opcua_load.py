"""An OPC UA client subscribed to every variable of the Cell at 10 Hz, as an HMI would be: the load
`clothd bench loop --opcua` puts beside the HTTP and WebSocket clients. It runs in a process of its own,
so that its work does not delay the bench's /status timer."""

from __future__ import annotations

import asyncio
from typing import Any

from asyncua import Client, Node, ua

NAMESPACE_URI = "urn:clothd:cell"  # as a client knows it, from docs/opcua.md
PUBLISH_MS = 100.0  # 10 Hz: the server's own publish rate


class _Count:
    def __init__(self) -> None:
        self.notifications = 0

    def datachange_notification(self, node: Node, val: Any, data: Any) -> None:
        self.notifications += 1


async def subscribe(url: str, seconds: float) -> int:
    """Data-change notifications received in `seconds`."""
    client = Client(url)
    client.session_timeout = 600_000  # ms: what asyncua's server grants at most (else it warns)
    async with client:
        idx = await client.get_namespace_index(NAMESPACE_URI)
        nodes = await _variables(await client.nodes.objects.get_child(f"{idx}:Cell"), idx)
        count = _Count()
        sub = await client.create_subscription(PUBLISH_MS, count)
        await sub.subscribe_data_change(nodes, queuesize=1)
        await asyncio.sleep(seconds)
        await sub.delete()
        return count.notifications


async def _variables(node: Node, idx: int) -> list[Node]:
    """Every variable of ours below `node`, found by browsing as an HMI would."""
    found = []
    for child in await node.get_children():
        if child.nodeid.NamespaceIndex != idx:
            continue
        if await child.read_node_class() == ua.NodeClass.Variable:
            found.append(child)
        else:
            found += await _variables(child, idx)
    return found


def subscriber_process(url: str, seconds: float, result: Any) -> None:
    """multiprocessing target: the count into `result` (a shared Value)."""
    try:
        result.value = asyncio.run(subscribe(url, seconds))
    except (OSError, ua.UaError, TimeoutError):
        result.value = -1  # the bench reports it as no notifications at all
