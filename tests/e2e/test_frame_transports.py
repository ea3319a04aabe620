"""The emulator's frame server and the companion's frame source over both transports
(docs/reference/wire.md): TCP and shared memory deliver the same frames, header and pixels."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from companion.camera import open_camera
from sim_bridge.camera.frames import FrameServer


@pytest.mark.parametrize("encoding", ["mono8", "bgr8", "png"])
def test_tcp_and_shared_memory_deliver_the_same_frames(encoding: str) -> None:
    shape = (120, 160, 3) if encoding == "bgr8" else (120, 160)
    images = [np.random.default_rng(s).integers(0, 256, shape, dtype=np.uint8)
              for s in range(12)]

    async def main() -> tuple[list[tuple[int, int, bytes]], ...]:
        async with FrameServer("127.0.0.1", 0, encoding) as srv:
            url = f"tcp://127.0.0.1:{srv.port}?frames=all"
            tcp = open_camera(url, queue_size=1)
            shm = open_camera(url + "&transport=shm", queue_size=1)
            got: tuple[list[tuple[int, int, bytes]], ...] = ([], [])
            async with tcp, shm:
                while srv.n_clients < 2:
                    await asyncio.sleep(0.01)
                await asyncio.sleep(0.2)  # the shared-memory request is read
                for seq, img in enumerate(images):  # in lockstep: each taken before the next
                    await srv.publish(seq, 50_000 * seq, img)
                    for cam, out in zip((tcp, shm), got, strict=True):
                        f = await asyncio.wait_for(anext(cam), 10.0)
                        out.append((f.seq, f.t_us, f.image.tobytes()))
                assert tcp.stats.torn_frames == shm.stats.torn_frames == 0
        assert srv._ring is not None and not srv._ring.path.exists()  # removed on close
        return got

    by_tcp, by_shm = asyncio.run(asyncio.wait_for(main(), 30.0))
    assert by_tcp == by_shm == [(s, 50_000 * s, im.tobytes()) for s, im in enumerate(images)]
