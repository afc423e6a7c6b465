"""The set-up cache (voxnerf/training/setup_cache.py): keys over exact inputs, loads instead of computing, recasts
what it cannot read, evicts the least recently used; and two runs of one scene, the second loading its casts."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic_fixtures import make_micro_scene, micro_config

from voxnerf.training import setup_cache
from voxnerf.training.run import train
from voxnerf.training.stages import FROM_CACHE

CPU = torch.device("cpu")
SHAPE = (2, 3, 4)


@pytest.fixture
def cache(monkeypatch, tmp_path) -> Path:
    monkeypatch.setenv("VOXNERF_CACHE", str(tmp_path))
    return tmp_path / "setup"


def _result(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    t = torch.rand(SHAPE, generator=torch.Generator().manual_seed(seed))
    ok = t > 0.3
    return torch.where(ok, t, torch.full_like(t, float("nan"))), ok


class Counting:
    def __init__(self, seed: int = 0) -> None:
        self.calls, self.seed = 0, seed

    def __call__(self):
        self.calls += 1
        return _result(self.seed)


def test_the_key_follows_every_input_value_shape_dtype_and_name():
    base = ["rays", torch.arange(6.0).view(2, 3), np.zeros(3), None, {"b": 1, "a": (2, 3.5)}]
    key = setup_cache.cache_key("first_hit", base, CPU)
    assert key == setup_cache.cache_key("first_hit", [*base[:1], torch.arange(6.0).view(2, 3), *base[2:]], CPU)
    changed = [
        ["rays", torch.arange(6.0).view(3, 2), *base[2:]],
        ["rays", torch.arange(6.0).view(2, 3).double(), *base[2:]],
        ["rays", torch.arange(6.0).view(2, 3) + 1e-7, *base[2:]],
        [*base[:4], {"b": 1, "a": (2, 3.25)}],
        [*base[:3], 0, base[4]],
    ]
    keys = {setup_cache.cache_key("first_hit", inputs, CPU) for inputs in changed}
    keys |= {setup_cache.cache_key("pseudo_depth", base, CPU), setup_cache.cache_key("first_hit", base,
                                                                                      torch.device("meta"))}
    assert key not in keys and len(keys) == len(changed) + 2
    with pytest.raises(TypeError, match="cannot key the set-up cache on a object"):
        setup_cache.cache_key("x", [object()], CPU)


def test_a_second_cast_of_the_same_inputs_loads_the_first(cache):
    compute = Counting()
    first, loaded = setup_cache.cached_per_pixel("cast", ["a"], SHAPE, CPU, compute)
    again, loaded_again = setup_cache.cached_per_pixel("cast", ["a"], SHAPE, CPU, compute)
    assert (loaded, loaded_again, compute.calls) == (False, True, 1)
    torch.testing.assert_close(again, first, equal_nan=True)
    other, loaded_other = setup_cache.cached_per_pixel("cast", ["b"], SHAPE, CPU, Counting(seed=1))
    assert not loaded_other and not torch.equal(other[1], first[1])
    assert len(list(cache.glob("*.pt"))) == 2


def test_a_disabled_cache_casts_every_time_and_writes_nothing(cache):
    compute = Counting()
    for _ in range(2):
        _, loaded = setup_cache.cached_per_pixel("cast", ["a"], SHAPE, CPU, compute, enabled=False)
        assert not loaded
    assert compute.calls == 2 and not cache.exists()


@pytest.mark.parametrize("damage", ["truncated", "garbage", "other_shape", "other_dtype"])
def test_an_entry_it_cannot_use_is_cast_again_and_rewritten(cache, damage):
    setup_cache.cached_per_pixel("cast", ["a"], SHAPE, CPU, Counting())
    (path,) = cache.glob("*.pt")
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:50])
    elif damage == "garbage":
        path.write_bytes(b"not a torch file")
    else:
        t, ok = _result()
        t = t[:1] if damage == "other_shape" else t.double()
        torch.save({"t": t, "ok": ok[: len(t)]}, path)
    compute = Counting()
    result, loaded = setup_cache.cached_per_pixel("cast", ["a"], SHAPE, CPU, compute)
    assert not loaded and compute.calls == 1
    again, loaded_again = setup_cache.cached_per_pixel("cast", ["a"], SHAPE, CPU, compute)
    assert loaded_again and compute.calls == 1
    torch.testing.assert_close(again, result, equal_nan=True)


@pytest.mark.parametrize("stored", ["refused", "not_a_dict", "not_tensors"])
def test_an_entry_of_tensors_its_check_refuses_is_computed_again(cache, stored):
    calls = []

    def compute():
        calls.append(1)
        return {"mask": torch.tensor([True, False]), "counts": torch.tensor([3, 4])}

    def fits(entry):
        return entry["mask"].shape == (2,) and entry["mask"].dtype == torch.bool

    first, loaded = setup_cache.cached("carve", ["a"], CPU, compute, fits)
    again, loaded_again = setup_cache.cached("carve", ["a"], CPU, compute, fits)
    assert (loaded, loaded_again, len(calls)) == (False, True, 1)
    assert all(torch.equal(again[key], first[key]) for key in first)
    (path,) = cache.glob("*.pt")
    bad = {"refused": {"mask": torch.ones(3, dtype=torch.bool), "counts": torch.tensor([3, 4])},
           "not_a_dict": [torch.ones(2)], "not_tensors": {"mask": [True, False], "counts": 3}}[stored]
    torch.save(bad, path)
    result, loaded = setup_cache.cached("carve", ["a"], CPU, compute, fits)
    assert not loaded and len(calls) == 2 and torch.equal(result["mask"], first["mask"])


def test_an_unwritable_cache_is_no_error(monkeypatch, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setenv("VOXNERF_CACHE", str(blocker))  # its 'setup' directory cannot be made
    result, loaded = setup_cache.cached_per_pixel("cast", ["a"], SHAPE, CPU, Counting())
    assert not loaded and result[0].shape == SHAPE


def test_eviction_removes_the_least_recently_used_first(tmp_path):
    for i, name in enumerate(["old", "used", "new"]):
        (tmp_path / f"{name}.pt").write_bytes(b"x" * 100)
        os.utime(tmp_path / f"{name}.pt", ns=(10**9 * i, 10**9 * i))
    os.utime(tmp_path / "used.pt", ns=(10**10, 10**10))  # loaded lately
    setup_cache.evict(tmp_path, 250)
    assert sorted(p.name for p in tmp_path.glob("*.pt")) == ["new.pt", "used.pt"]
    setup_cache.evict(tmp_path, 0)
    assert not list(tmp_path.glob("*.pt"))


def test_a_second_run_of_a_scene_loads_its_casts_and_trains_alike(cache, tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "setup-cache")
    reports = [train(room, tmp_path / f"run{i}", micro_config(final_eval=False), progress_bar=False)
               for i in range(2)]
    whys = [{s.name: s.why for s in r.stages} for r in reports]
    for stage in ("pseudo_depth", "octree_carving", "first_hit_cache"):
        assert FROM_CACHE not in whys[0][stage] and whys[1][stage] == whys[0][stage] + FROM_CACHE, stage
    assert len(list(cache.glob("*.pt"))) == 3
    assert reports[1].octree == reports[0].octree  # the carving loaded removes the same leaves
    fields = [torch.load(tmp_path / f"run{i}" / "checkpoint.pt", weights_only=True)["model"]["field"]
              for i in range(2)]
    for name, value in fields[0].items():
        torch.testing.assert_close(fields[1][name], value, rtol=1e-4, atol=1e-6)
    uncached = train(room, tmp_path / "run3", micro_config(final_eval=False, setup_cache=False),
                     progress_bar=False)
    assert all(FROM_CACHE not in s.why for s in uncached.stages)


def test_the_window_centre_rule_keys_its_cast_and_puts_the_centre_nearer_the_depth(cache, tmp_path_factory, tmp_path):
    """A run centring the sampler's window on the prior's surface casts its own first hits (the entry run's cached
    ones are not reused) and its centres lie nearer the depth maps' surface than the leaf entries do."""
    room = make_micro_scene(tmp_path_factory, "setup-cache")
    reports = {centre: train(room, tmp_path / centre, micro_config(final_eval=False, window_centre=centre),
                             progress_bar=False) for centre in ("entry", "surface")}
    whys = {centre: {s.name: s.why for s in r.stages} for centre, r in reports.items()}
    assert "window centre: entry" in whys["entry"]["first_hit_cache"]
    assert "window centre: surface" in whys["surface"]["first_hit_cache"]
    assert FROM_CACHE not in whys["surface"]["first_hit_cache"]
    assert {c: r.window_check["window"]["centre"] for c, r in reports.items()} == {c: c for c in reports}
    offsets = {centre: r.window_check["first_hit_offset_m"]["p50"] for centre, r in reports.items()}
    assert offsets["entry"] < 0 and abs(offsets["surface"]) < abs(offsets["entry"]), offsets
