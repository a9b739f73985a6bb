"""Frames of the simulated camera side by side (uw_sil.sim.stream)."""
import threading

import numpy as np
import pytest

from uw_sil.sim.camera import CameraModel
from uw_sil.sim.scene import facing_pose
from uw_sil.sim.simcam import SimCamera
from uw_sil.sim.stream import FrameStream

CAM = CameraModel.from_fov(80, 60)
POSES = [facing_pose(3.0 - 0.2 * k, yaw=0.05 * k) for k in range(8)]
KW = dict(camera=CAM, effects="marine_snow=strong,sensor_noise=mild,pose_error=mild", noise_sigma=1.5, seed=9)


def test_frames_come_out_in_order_and_equal_to_one_at_a_time_even_when_models_finish_out_of_order():
    with SimCamera(**KW) as cam:
        ref = [cam.render(T) for T in POSES]
    with SimCamera(**KW) as cam:
        finish, calls, order = cam.finish, iter(range(100)), []
        done = [threading.Event() for _ in POSES]

        def slow_even(job, raw):
            # every other model waits until the next one has finished: later frames finish first, whatever the
            # load (a sleep of 50 ms did not reorder them on a loaded machine). Only a stream that cannot run two
            # models at once would wait out the timeout.
            k = next(calls)
            if k % 2 == 0 and k + 1 < len(POSES):
                done[k + 1].wait(timeout=60.0)
            frame = finish(job, raw)
            order.append(k)
            done[k].set()
            return frame

        cam.finish = slow_even
        got, threads = [], set()
        with FrameStream(cam, lambda tag, f, e: (got.append((tag, f, e)), threads.add(threading.get_ident())),
                         workers=3) as stream:
            for k, T in enumerate(POSES):
                stream.submit(T, tag=k)
    assert order != sorted(order)                          # the models did finish out of order
    assert [t for t, _, _ in got] == list(range(len(POSES)))
    assert all(e is None for _, _, e in got)
    for (_, f, _), r in zip(got, ref):
        np.testing.assert_array_equal(f.image, r.image)
        np.testing.assert_array_equal(f.render.depth, r.render.depth)
    assert threading.get_ident() not in threads


def test_a_failed_frame_is_delivered_as_its_error_and_the_others_still_come():
    with SimCamera(camera=CAM) as cam:
        got = []
        with FrameStream(cam, lambda tag, f, e: got.append((tag, f is not None, type(e).__name__))) as stream:
            stream.submit(POSES[0], tag="a")
            stream.submit(np.full((4, 4), np.nan), tag="bad")     # the renderer rejects it
            stream.submit(POSES[1], tag="b")
    assert got == [("a", True, "NoneType"), ("bad", False, "ValueError"), ("b", True, "NoneType")]


def test_an_exception_in_deliver_is_raised_by_close_after_every_frame_was_delivered():
    seen = []

    def deliver(tag, frame, error):
        seen.append(tag)
        if tag == 1:
            raise KeyError("publisher gone")

    with SimCamera(camera=CAM) as cam:
        stream = FrameStream(cam, deliver, workers=2)
        for k in range(4):
            stream.submit(POSES[k], image=False, tag=k)
        with pytest.raises(KeyError, match="publisher gone"):
            stream.close()
        with pytest.raises(RuntimeError, match="closed"):
            stream.submit(POSES[0])
    assert seen == [0, 1, 2, 3]


def test_stream_frames_yields_the_frames_in_order_raises_a_failure_and_can_be_left_early():
    from uw_sil.sim.stream import stream_frames

    with SimCamera(**KW) as cam:
        ref = [cam.render(T).image for T in POSES]
    with SimCamera(**KW) as cam:
        got = [f.image for f in stream_frames(cam, POSES)]
    assert len(got) == len(ref) and all(np.array_equal(a, b) for a, b in zip(got, ref))
    with SimCamera(camera=CAM) as cam:
        frames = stream_frames(cam, [POSES[0], np.full((4, 4), np.nan), POSES[1]])
        assert next(frames).image is not None
        with pytest.raises(ValueError, match="finite"):
            next(frames)
        frames = stream_frames(cam, POSES)
        next(frames)
        frames.close()                              # the rest is made and dropped; the camera is free again
        assert cam.render(POSES[2]).image is not None


def test_newest_only_drops_waiting_frames_never_the_newest_and_delivers_in_order():
    """A live camera: poses faster than frames are made; the ones that waited are replaced, the rest come out in
    order, and the last pose submitted is always made."""
    with SimCamera(camera=CAM) as cam:
        finish = cam.finish
        burst_in = threading.Event()

        def slow(job, raw):
            # no frame is finished before the whole burst is in: poses come faster than frames, whatever the load
            # (a sleep of 30 ms per frame relied on the submitting thread being faster)
            burst_in.wait(timeout=60.0)
            return finish(job, raw)

        cam.finish = slow
        got = []
        with FrameStream(cam, lambda tag, f, e: got.append((tag, e)), workers=1, newest_only=True) as stream:
            for k in range(12):
                stream.submit(POSES[k % len(POSES)], tag=k)
            burst_in.set()
    tags = [t for t, _ in got]
    assert all(e is None for _, e in got)
    assert tags == sorted(tags) and tags[-1] == 11
    assert stream.dropped > 0 and len(tags) + stream.dropped == 12
