"""Tests of uw_sil.bags.stamps: offline pairing against brute force, online synchronizer against offline."""
import random

import numpy as np
import pytest

from uw_sil.bags.stamps import StampSynchronizer, SyncStats, pair_by_stamp, seconds_to_ns

MS = 1_000_000


def brute_force(primary, secondaries, tol_ns):
    """Nearest partner by exhaustive search: minimal |dt|, then earlier stamp, then last received."""
    out = []
    for t, item in sorted(primary, key=lambda p: p[0]):
        items, stamps = [item], [t]
        for k, sec in enumerate(secondaries):
            if not sec:
                break
            order = sorted(range(len(sec)), key=lambda i: sec[i][0])
            best = min(order, key=lambda i: (abs(sec[i][0] - t), sec[i][0], -order.index(i)))
            if tol_ns[k] is not None and abs(sec[best][0] - t) > tol_ns[k]:
                break
            items.append(sec[best][1])
            stamps.append(sec[best][0])
        else:
            out.append((t, tuple(items), tuple(stamps)))
    return out


def as_tuples(matches):
    return [(m.stamp_ns, m.items, m.stamps_ns) for m in matches]


def run_online(sync, arrivals):
    """arrivals: list of (stream, stamp, item) in arrival order."""
    out = []
    for k, t, x in arrivals:
        out += sync.add(k, t, x)
    return out + sync.flush()


def test_exact_stamps_all_matched():
    stamps = [10**9 + i * 33 * MS for i in range(30)]
    img = [(t, f"img{i}") for i, t in enumerate(stamps)]
    info = [(t, f"info{i}") for i, t in enumerate(stamps)]
    pose = [(t, f"pose{i}") for i, t in enumerate(stamps)]
    stats = SyncStats()
    m = pair_by_stamp(img, info, pose, max_dt=0.001, stats=stats)
    assert [x.items for x in m] == [(f"img{i}", f"info{i}", f"pose{i}") for i in range(30)]
    assert stats.matched == stats.exact == 30 and stats.dropped == 0
    assert all(x.dt_ns == (0, 0) for x in m)
    # online: interleaved image, info, pose per frame -> each match final as soon as its pose arrives
    sync = StampSynchronizer(3, max_dt=0.001)
    decided_at = []
    for i, t in enumerate(stamps):
        assert sync.add(0, t, f"img{i}") == [] and sync.add(1, t, f"info{i}") == []
        got = sync.add(2, t, f"pose{i}")
        decided_at.append(len(got))
    assert decided_at == [1] * 30 and sync.pending == 0 and sync.flush() == []
    assert sync.stats.exact == 30


def test_exact_match_preferred_over_nearer_neighbours():
    prim = [(100, "a")]
    sec = [(99, "before"), (100, "exact"), (101, "after")]
    assert pair_by_stamp(prim, sec, max_dt=1.0)[0].items == ("a", "exact")
    # tie between an earlier and a later message: the earlier wins
    assert pair_by_stamp([(100, "a")], [(98, "early"), (102, "late")], max_dt=1.0)[0].items == ("a", "early")
    # duplicate stamps within a stream: the last received wins (offline and online)
    dup = [(100, "first"), (100, "second")]
    assert pair_by_stamp(prim, dup, max_dt=1.0)[0].items == ("a", "second")
    sync = StampSynchronizer(2, max_dt=1.0)
    got = run_online(sync, [(1, 100, "first"), (1, 100, "second"), (0, 100, "a")])
    assert got[0].items == ("a", "second")


def test_jittered_streams_pair_with_their_own_message():
    rng = np.random.default_rng(1)
    n = 200
    base = 5 * 10**9 + np.arange(n) * 33 * MS
    img = [(int(t), i) for i, t in enumerate(base)]
    pose = [(int(t + rng.integers(-5 * MS, 5 * MS)), i) for i, t in enumerate(base)]
    m = pair_by_stamp(img, pose, max_dt=0.010)
    assert len(m) == n and all(x.items[0] == x.items[1] for x in m)
    assert max(abs(x.dt_ns[0]) for x in m) < 5 * MS
    # online, pose delivered 20 ms after the image (processing latency), in order within each stream
    arrivals = sorted([(t, 0, t, i) for t, i in img] + [(t + 20 * MS, 1, t, i) for t, i in pose])
    sync = StampSynchronizer(2, max_dt=0.010)
    got = run_online(sync, [(k, t, i) for _, k, t, i in arrivals])
    assert as_tuples(got) == as_tuples(m)


def test_dropped_messages_drop_or_fall_back_to_neighbour():
    period = 100 * MS
    img = [(i * period, i) for i in range(20)]
    missing = {3, 4, 11}
    pose = [(i * period + 2 * MS, i) for i in range(20) if i not in missing]
    stats = SyncStats()
    m = pair_by_stamp(img, pose, max_dt=0.010, stats=stats)
    assert sorted(x.items[0] for x in m) == [i for i in range(20) if i not in missing]
    assert stats.dropped_no_partner == [0, 3] and stats.dropped == 3
    # with a tolerance above the period the neighbour is used instead (nearest: 98 ms vs 202 ms away)
    m2 = pair_by_stamp(img, pose, max_dt=0.150)
    assert len(m2) == 20
    assert {x.items[0]: x.items[1] for x in m2}[3] == 2 and {x.items[0]: x.items[1] for x in m2}[4] == 5


def test_out_of_order_within_lateness_matches_offline():
    rng = random.Random(7)
    period = 50 * MS
    img = [(i * period, f"i{i}") for i in range(100)]
    pose = [(i * period + rng.randint(-3, 3) * MS, f"p{i}") for i in range(100)]
    expected = pair_by_stamp(img, pose, max_dt=0.02)
    # deliver each stream with local swaps: a message may be up to 2 periods (100 ms) late
    def shuffled(stream):
        s = list(stream)
        for i in range(0, len(s) - 2, 3):
            s[i], s[i + 2] = s[i + 2], s[i]
        return s
    arrivals = []
    for a, b in zip(shuffled(img), shuffled(pose)):
        arrivals += [(0, *a), (1, *b)]
    sync = StampSynchronizer(2, max_dt=0.02, lateness=0.15)
    got = run_online(sync, arrivals)
    assert sorted(as_tuples(got)) == sorted(as_tuples(expected))
    assert sync.stats.forced == 0
    # without lateness tolerance the same delivery pairs some images with a worse partner or drops them
    sync0 = StampSynchronizer(2, max_dt=0.02, lateness=0.0)
    assert sorted(as_tuples(run_online(sync0, arrivals))) != sorted(as_tuples(expected))


def test_slow_camera_info_is_reused():
    img = [(i * 100 * MS, i) for i in range(50)]  # 10 Hz
    info = [(i * 1000 * MS, f"info{i}") for i in range(5)]  # 1 Hz
    m = pair_by_stamp(img, info, max_dt=None)
    assert len(m) == 50
    for i, x in enumerate(m):
        # nearest 1 Hz message; at exactly half-way (0.5 s, 1.5 s...) the earlier one wins
        assert x.items == (i, f"info{min(4, (i + 4) // 10)}")
    arrivals = sorted([(t, 0, t, i) for t, i in img] + [(t, 1, t, s) for t, s in info])
    sync = StampSynchronizer(2, max_dt=None, queue_size=1000)
    assert as_tuples(run_online(sync, [a[1:] for a in arrivals])) == as_tuples(m)


@pytest.mark.parametrize("seed", range(8))
def test_offline_equals_brute_force_and_online_equals_offline(seed):
    rng = random.Random(seed)
    n = rng.randint(0, 60)
    prim = sorted(rng.sample(range(0, 10**6, 7), n))
    prim = [(t * 1000, f"p{i}") for i, t in enumerate(prim)]
    secs = []
    for k in range(2):
        m = rng.randint(0, 60)
        st = sorted(rng.randint(0, 10**6) * 1000 for _ in range(m))  # may contain duplicates
        secs.append([(t, f"s{k}_{i}") for i, t in enumerate(st)])
    tol = [rng.choice([None, 0.0, 0.005, 0.05]), rng.choice([None, 0.02])]
    tol_ns = [seconds_to_ns(x) for x in tol]
    off = pair_by_stamp(prim, *secs, max_dt=tol)
    assert as_tuples(off) == brute_force(prim, secs, tol_ns)
    # online: each stream in order, streams delayed by different random latencies
    arrivals = []
    for k, stream in enumerate([prim] + secs):
        delay = rng.randint(0, 30_000_000)
        arrivals += [(t + delay, idx, k, t, x) for idx, (t, x) in enumerate(stream)]
    arrivals.sort()
    sync = StampSynchronizer(3, max_dt=tol, queue_size=10**6)
    on = run_online(sync, [(k, t, x) for _, _, k, t, x in arrivals])
    assert as_tuples(on) == as_tuples(off)
    assert sync.stats.matched == len(off)
    assert sync.stats.received == [len(prim), len(secs[0]), len(secs[1])]


def test_memory_stays_bounded_and_queue_overflow_is_counted():
    sync = StampSynchronizer(2, max_dt=0.01, queue_size=5, buffer_size=1000)
    n_out = 0
    for i in range(5000):
        n_out += len(sync.add(0, i * 10 * MS, i))
        n_out += len(sync.add(1, i * 10 * MS + MS, i))
        assert len(sync._stamps[1]) <= 3 and sync.pending <= 1
    assert n_out == 5000 and sync.flush() == []  # each image final once the pose 1 ms after it arrives
    # a secondary stream that never delivers: images pile up to queue_size, then are decided (dropped)
    sync = StampSynchronizer(2, max_dt=0.01, queue_size=5)
    out = [m for i in range(20) for m in sync.add(0, i * MS, i)]
    assert out == [] and sync.pending == 5
    assert sync.stats.forced == 15 and sync.stats.dropped == 15
    # a stalled primary: secondary buffer capped at buffer_size
    sync = StampSynchronizer(2, max_dt=0.01, buffer_size=10)
    for i in range(25):
        sync.add(1, i, i)
    assert len(sync._stamps[1]) == 10 and sync.stats.secondary_overflow[1] == 15


def test_validation_errors():
    with pytest.raises(ValueError, match="at least 2 streams"):
        StampSynchronizer(1)
    with pytest.raises(ValueError, match=">= 0 seconds"):
        StampSynchronizer(2, max_dt=-0.1)
    with pytest.raises(ValueError, match="2 entries but there are 1"):
        pair_by_stamp([(0, 0)], [(0, 0)], max_dt=[0.1, 0.1])
    with pytest.raises(TypeError, match="integer nanoseconds"):
        pair_by_stamp([(1.5, "x")], [(1, "y")])
    sync = StampSynchronizer(2)
    with pytest.raises(IndexError):
        sync.add(2, 0, None)
    with pytest.raises(TypeError, match="integer nanoseconds"):
        sync.add(0, 0.5, None)
    assert seconds_to_ns(float("inf")) is None and seconds_to_ns(0.25) == 250 * MS


# ---------------------------------------------------------------------------------------------
# The tolerance boundary: |dt| == max_dt pairs, one nanosecond more does not, max_dt = 0 keeps exact pairs


def _boundary_cases():
    tol = 50 * MS                                       # max_dt = 0.05 s is exactly 50_000_000 ns
    t0 = 10**9
    yield 0.05, t0, t0 + tol, True                      # later partner exactly at the tolerance
    yield 0.05, t0, t0 - tol, True                      # earlier partner exactly at the tolerance
    yield 0.05, t0, t0 + tol + 1, False                 # 1 ns beyond
    yield 0.05, t0, t0 - tol - 1, False
    yield 0.0, t0, t0, True                             # tolerance 0: exact stamps pair
    yield 0.0, t0, t0 + 1, False                        # ... and nothing else


@pytest.mark.parametrize("max_dt, t_img, t_pose, pairs", list(_boundary_cases()))
def test_tolerance_boundary_offline(max_dt, t_img, t_pose, pairs):
    stats = SyncStats()
    m = pair_by_stamp([(t_img, "img")], [(t_pose, "pose")], max_dt=max_dt, stats=stats)
    assert as_tuples(m) == ([(t_img, ("img", "pose"), (t_img, t_pose))] if pairs else [])
    assert stats.dropped == (0 if pairs else 1)


@pytest.mark.parametrize("pose_first", [True, False])
@pytest.mark.parametrize("max_dt, t_img, t_pose, pairs", list(_boundary_cases()))
def test_tolerance_boundary_online(max_dt, t_img, t_pose, pairs, pose_first):
    expected = [(t_img, ("img", "pose"), (t_img, t_pose))] if pairs else []
    # decided by later traffic on the pose stream (one second on), not by flush()
    arrivals = [(0, t_img, "img"), (1, t_pose, "pose")]
    if pose_first:
        arrivals.reverse()
    sync = StampSynchronizer(2, max_dt=max_dt)
    decided = []
    for k, t, x in arrivals + [(1, t_img + 10**9, "later")]:
        decided += sync.add(k, t, x)
    assert as_tuples(decided) == expected and sync.pending == 0
    assert sync.stats.dropped == (0 if pairs else 1)
    # and decided at the end of the input
    sync = StampSynchronizer(2, max_dt=max_dt)
    assert as_tuples(run_online(sync, arrivals)) == expected


def test_tolerance_boundary_in_a_bag(tmp_path):
    """read_samples: a pose exactly max_dt after its image pairs, one 1 ns further does not."""
    from uw_sil.bags import Sample, read_samples, write_trial
    from uw_sil.sim.camera import CameraModel

    cam = CameraModel.from_fov(16, 12)
    img = np.random.default_rng(0).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    t0 = 1_700_000_000_000_000_000
    bag = write_trial(tmp_path / "b.mcap", [Sample(t0 + i * 10**9, img, cam, np.eye(4)) for i in range(3)],
                      write_tf=False)
    # the same bag with the poses moved: +50 ms, -50 ms, +50 ms + 1 ns
    from rosbags.rosbag2 import Reader, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_KILTED)
    shifted = tmp_path / "shifted"
    with Reader(bag) as r, Writer(shifted, version=9) as w:
        conns = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in r.connections}
        n = 0
        for c, t, data in r.messages():
            if c.topic == "/panel/pose":
                msg = ts.deserialize_cdr(data, c.msgtype)
                s = t + (50 * MS, -50 * MS, 50 * MS + 1)[n]
                n += 1
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(s, 10**9)
                data = ts.serialize_cdr(msg, c.msgtype)
            w.write(conns[c.topic], t, data)
    stream = read_samples(shifted, max_dt=0.05)
    assert [s.stamp_ns for s in stream] == [t0, t0 + 10**9]
    assert stream.report.sync.dropped == 1
    assert [s.stamp_ns for s in read_samples(bag, max_dt=0.0)] == [t0 + i * 10**9 for i in range(3)]
