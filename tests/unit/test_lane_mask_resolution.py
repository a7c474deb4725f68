"""Centralized mode sends the lane mask at the resolution the host's matcher uses.

The vehicle pools with the matcher's own function (lanemask.pool) and sends the result in
``lane_mask_pooled_png``, so the host sees the same pixels whichever of the two pooled: its poses are
the same as with the mask at camera resolution in ``lane_mask_png``, which is what a vehicle sent
before and what an older vehicle still sends.
"""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from mapcontainer import lanemask
from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.joint import JointHost
from mapcontainer.localization import MatcherParams
from mapcontainer.sim import World, load_scenario
from mapcontainer.vehicle import VehicleAgent, camera_frame
from schemas import RawObservations, Rejection, SensorFrame, decode, encode
from schemas.tags import TAGS

SEED = 90000
FULL = 1 << 30  # raw_mask_max_width_px that never pools: the mask as the camera makes it
WIDTH = MatcherParams().lane_dt_max_width_px


def _reference_pool(mask: np.ndarray, k: int) -> np.ndarray:
    """Max-pooling by k written out: a k x k block is marking if any pixel in it is."""
    h, w = mask.shape[0] // k * k, mask.shape[1] // k * k
    blocks = mask[:h, :w].reshape(h // k, k, w // k, k)
    return np.where(blocks.max(axis=(1, 3)) > 0, 255, 0).astype(np.uint8)


@pytest.mark.parametrize(("w", "max_w", "k"), [(1280, 640, 2), (640, 640, 1), (641, 640, 2), (1920, 640, 3), (1, 5, 1)])
def test_pool_factor(w, max_w, k):
    assert lanemask.pool_factor(w, max_w) == k


@pytest.mark.parametrize("shape", [(720, 1280), (721, 1283), (1080, 1920), (9, 700)])
def test_pool_is_max_pooling_and_pooling_twice_changes_nothing(shape):
    rng = np.random.default_rng(1)
    mask = np.where(rng.random(shape) < 0.02, 255, 0).astype(np.uint8)
    k = lanemask.pool_factor(shape[1], WIDTH)
    pooled = lanemask.pool(mask, WIDTH)
    assert pooled.shape[1] <= WIDTH
    assert np.array_equal(pooled, _reference_pool(mask, k))
    assert lanemask.pool(pooled, WIDTH) is pooled


def test_pool_png_passes_a_narrow_mask_through_and_pools_a_wide_one():
    rng = np.random.default_rng(2)
    mask = np.where(rng.random((720, 1280)) < 0.02, 255, 0).astype(np.uint8)
    png = lanemask.encode(mask)
    small = lanemask.pool_png(png, WIDTH)
    assert lanemask.png_size(small) == (640, 360)
    assert np.array_equal(lanemask.decode(small), lanemask.pool(mask, WIDTH))
    assert lanemask.pool_png(small, WIDTH) is small  # narrow enough: the same bytes, nothing decoded
    assert lanemask.pool_png(b"", WIDTH) == b""
    with pytest.raises(ValueError):
        lanemask.pool_png(b"\x89PNG\r\n\x1a\n" + b"\0" * 40, WIDTH)


def test_the_centralized_vehicle_sends_the_pooled_mask_and_the_camera_it_came_from():
    world = World(load_scenario("paper-urban"), seed=SEED)
    tick = next(iter(world.run(0.1)))
    vid, frame = next(iter(tick.frames.items()))
    raw = VehicleAgent(world.hdmap, vid, "sim", "centralized").handle(tick.t, frame)
    assert isinstance(raw, RawObservations)
    assert lanemask.png_size(frame.lane_mask_png) == (1280, 720)
    assert raw.lane_mask_png == b"" and lanemask.png_size(raw.lane_mask_pooled_png) == (640, 360)
    assert (raw.camera.width, raw.camera.height) == (1280, 720)  # the intrinsics stay the camera's
    assert len(raw.lane_mask_pooled_png) < len(frame.lane_mask_png) / 1.5
    # the host's matcher sees the pixels it would have pooled itself
    full = camera_frame(frame).lane_mask
    assert np.array_equal(camera_frame(decode(encode(raw), RawObservations)).lane_mask, lanemask.pool(full, WIDTH))
    full_agent = VehicleAgent(world.hdmap, vid, "sim", "centralized", raw_mask_max_width_px=FULL)
    as_before = full_agent.handle(tick.t, frame)
    assert as_before.lane_mask_png == frame.lane_mask_png and as_before.lane_mask_pooled_png is None
    assert TAGS["lane_mask_pooled_png"] not in msgpack.unpackb(encode(as_before), strict_map_key=False)
    with pytest.raises(ValueError):
        VehicleAgent(world.hdmap, vid, "sim", "centralized", raw_mask_max_width_px=0)


def test_the_hosts_poses_are_the_same_with_the_mask_at_camera_or_at_matcher_resolution():
    """Two centralized hosts of one run, one fed the masks at 1280x720 (as vehicles sent them before,
    and as an older vehicle still does), one at 640x360: every fused pose and every host-side
    localizer's pose is the same to the bit (max difference 0)."""
    world = World(load_scenario("paper-urban"), seed=SEED)
    ids = world.vehicle_ids
    variants = {"camera": FULL, "matcher": None}
    agents = {
        name: {v: VehicleAgent(world.hdmap, v, "sim", "centralized", raw_mask_max_width_px=w) for v in ids}
        for name, w in variants.items()
    }
    hosts = {name: JointHost(world.hdmap, FusionParams(), "sim", "host", set(ids)) for name in variants}
    sizes = {name: [] for name in variants}
    max_diff, fused_poses = 0.0, 0
    for tick in world.run(3.0):
        fused = {}
        for name in variants:
            for vid, frame in tick.frames.items():
                payload = encode(agents[name][vid].handle(tick.t, frame))
                sizes[name].append(len(payload))
                hosts[name].ingest(payload, tick.t)
            fused[name] = hosts[name].fuse(tick.t)
        a, b = fused["camera"], fused["matcher"]
        assert a.vehicle_ids == b.vehicle_ids
        pa, pb = np.asarray(a.vehicle_pose, float), np.asarray(b.vehicle_pose, float)
        assert pa.shape == pb.shape
        if pa.size:
            max_diff = max(max_diff, float(np.max(np.abs(pa - pb))))
            fused_poses += len(pa)
        assert np.array_equal(np.asarray(a.object_p_map), np.asarray(b.object_p_map))
        for vid in ids:  # each host-side localizer's own pose of the vehicle
            la, lb = (hosts[name].localizers.get(vid) for name in variants)
            assert (la is None) == (lb is None)
            la, lb = (None, None) if la is None else (la.pose, lb.pose)
            assert (la is None) == (lb is None)
            if la is not None:
                max_diff = max(max_diff, float(np.max(np.abs(la - lb))))
    assert fused_poses > 50  # the hosts did localize and fuse the vehicles
    assert max_diff == 0.0
    assert np.mean(sizes["matcher"]) < 0.6 * np.mean(sizes["camera"])


def _raw(world_seed: int = SEED) -> tuple[RawObservations, SensorFrame]:
    world = World(load_scenario("paper-urban"), seed=world_seed)
    tick = next(iter(world.run(0.1)))
    vid, frame = next(iter(tick.frames.items()))
    return VehicleAgent(world.hdmap, vid, "sim", "centralized").handle(tick.t, frame), frame


def test_a_pooled_mask_must_be_the_camera_divided_by_an_integer_and_alone():
    raw, frame = _raw()
    assert isinstance(decode(encode(raw), RawObservations), RawObservations)
    mask = lanemask.decode(raw.lane_mask_pooled_png)
    for bad_shape in [(361, 640), (360, 639), (720, 1281)]:  # not (720 // k, 1280 // k) for any integer k
        bad = np.zeros(bad_shape, np.uint8)
        msg = raw.model_copy(update={"lane_mask_pooled_png": lanemask.encode(bad)})
        assert isinstance(decode(encode(msg), RawObservations), Rejection)
    for ok_shape in [(240, 426), (720, 1280), mask.shape]:  # k = 3, 1, 2
        msg = raw.model_copy(update={"lane_mask_pooled_png": lanemask.encode(np.zeros(ok_shape, np.uint8))})
        assert isinstance(decode(encode(msg), RawObservations), RawObservations)
    both = raw.model_copy(update={"lane_mask_png": frame.lane_mask_png})
    assert decode(encode(both), RawObservations).reason == "invalid"
    not_png = raw.model_copy(update={"lane_mask_pooled_png": b"GIF89a" + bytes(30)})
    assert decode(encode(not_png), RawObservations).reason == "invalid"


def test_a_reader_that_does_not_know_the_pooled_field_sees_a_message_without_a_lane_mask():
    """The old contract holds: lane_mask_png is either the camera's resolution or empty; tag 94 is
    a new tag, which readers that do not know it skip."""
    raw, _ = _raw()
    wire = msgpack.unpackb(encode(raw), strict_map_key=False)
    assert wire[TAGS["lane_mask_png"]] == b""
    assert lanemask.png_size(wire[TAGS["lane_mask_pooled_png"]]) == (640, 360)
    del wire[TAGS["lane_mask_pooled_png"]]
    old = decode(msgpack.packb(wire, use_bin_type=True), RawObservations)
    assert isinstance(old, RawObservations) and camera_frame(old).lane_mask is None
