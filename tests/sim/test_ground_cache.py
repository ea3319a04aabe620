"""The ground texture's disk cache (sim_bridge/camera/scene.py): what a start reads from it is
the texture it would compute, and a damaged cache file is computed afresh."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim_bridge.camera import scene


def _fresh(seed: int) -> np.ndarray:
    return np.pad(scene.make_ground_texture(seed), scene._GROUND_PAD_PX, mode="wrap")


def test_cached_texture_is_the_computed_one(tmp_path: Path) -> None:
    first = scene.ground_texture(3, tmp_path)  # computes and stores
    files = list(tmp_path.glob("ground-*.npy"))
    assert len(files) == 1
    scene.ground_texture.cache_clear()
    second = scene.ground_texture(3, tmp_path)  # reads the file
    assert np.array_equal(first, _fresh(3))
    assert np.array_equal(second, first)
    assert not second.flags.writeable
    # another seed is another file and another texture
    other = scene.ground_texture(4, tmp_path)
    assert len(list(tmp_path.glob("ground-*.npy"))) == 2
    assert not np.array_equal(other, first)


def test_damaged_cache_file_is_recomputed(tmp_path: Path) -> None:
    scene.ground_texture(5, tmp_path)
    (path,) = tmp_path.glob("ground-*.npy")
    np.save(path, np.zeros((8, 8), np.uint8))  # wrong shape: not the texture
    scene.ground_texture.cache_clear()
    assert np.array_equal(scene.ground_texture(5, tmp_path), _fresh(5))
    path.write_bytes(b"not an npy file")
    scene.ground_texture.cache_clear()
    assert np.array_equal(scene.ground_texture(5, tmp_path), _fresh(5))


def test_unwritable_cache_still_renders(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache directory should be")
    scene.ground_texture.cache_clear()
    assert np.array_equal(scene.ground_texture(6, blocker / "sub"), _fresh(6))
