"""The helpers of the node tests (test/rosproc.py): domain ids no two tests share, even across processes;
failure messages that carry the tail of every node's log."""
import subprocess
import sys
from pathlib import Path

import pytest

import rosproc
from rosproc import Proc, domain_id, logs_on_failure, release_domains

HERE = Path(__file__).resolve().parent


def test_domain_ids_are_not_shared_between_processes():
    """A domain id reserved by another process (a concurrent test run) is not handed out here while that
    process holds it; ids are 1..232 (Fast DDS' ports end there)."""
    holder = subprocess.Popen([sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); import rosproc; "
                               "ids = [rosproc.domain_id() for _ in range(100)]; print(' '.join(map(str, ids)), "
                               "flush=True); sys.stdin.read()", str(HERE)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        theirs = set(map(int, holder.stdout.readline().split()))
        assert len(theirs) == 100 and all(1 <= d <= rosproc.N_DOMAINS for d in theirs)
        mine = {domain_id() for _ in range(20)}
        assert len(mine) == 20 and not mine & theirs
    finally:
        holder.stdin.close()          # the holder exits: its reservations go with it
        holder.wait(timeout=30)
    release_domains()


def test_failure_messages_carry_each_nodes_log_tail():
    """A launcher's output is split by node prefix, so a chatty node does not push another's last lines out
    of the message; the output is complete once the process has ended."""
    script = ("for i in range(100): print(f'[chatty] line {i}')\n"
              "print('[quiet ] [ERROR] [quiet]: the one line that matters')\n"
              "print('[launch] done: FAILED: quiet')\n")
    p = Proc([sys.executable, "-c", script], env=None, name="launcher")
    p.wait_group(30)
    with pytest.raises(AssertionError) as e:
        with logs_on_failure({"launch": p}):
            assert False, "what failed"
    text = str(e.value)
    assert text.startswith("what failed\n") and "--- launcher (pid " in text and "exit status 0" in text
    assert "the one line that matters" in text and "done: FAILED: quiet" in text
    assert "line 99" in text and "line 59" not in text        # the last 40 of the chatty node
    assert "-- [chatty] last 40 of 100:" in text


def test_a_node_that_does_not_stop_in_time_shows_its_stacks():
    """When a node process outlives the wait for it, the failure carries every thread's Python stack (asked
    for with SIGUSR1, which node processes hand to faulthandler), not only its last log lines: where it hangs.
    The hanging function here is named so that its frame can be found in the message."""
    script = ("import threading, uw_sil.nodes as un\n"
              "un._report_crashes()\n"
              "def stuck_in_teardown():\n"
              "    print('ready', flush=True)\n"
              "    threading.Event().wait()\n"
              "stuck_in_teardown()\n")
    p = Proc([sys.executable, "-c", script], env=None, name="stuck node")
    try:
        p.wait_for("ready", timeout=60)
        with pytest.raises(AssertionError) as e:
            p.wait_group(0.2)
        text = str(e.value)
        assert "stacks of the node processes" in text and "most recent call first" in text, text
        assert "in stuck_in_teardown" in text, text
        assert p.popen.poll() is None, "SIGUSR1 ended the process: the handler was not registered"
    finally:
        p.stop(timeout=5)


class _Future:
    def __init__(self, answer=None):
        self.answer = answer

    def done(self):
        return self.answer is not None

    def result(self):
        return self.answer


class _LosesFirstAnswers:
    """A service client whose first ``lost`` calls are never answered (Fast DDS dropped the answers) and whose
    later calls are answered at once with the call's number."""

    def __init__(self, lost: int):
        self.lost, self.calls = lost, 0

    def call_async(self, request):
        self.calls += 1
        return _Future(None if self.calls <= self.lost else f"answer to call {self.calls}")


class _Executor:
    def spin_once(self, timeout_sec=0.0):
        pass


def test_a_service_answer_lost_to_discovery_is_asked_for_again():
    """A service's answer dropped before the server matched the client (rmw_fastrtps issue 842) must not turn
    into a timeout: the call is repeated until one is answered; a service that never answers still fails, naming
    it and the number of calls."""
    from rosproc import call_until_answered

    client = _LosesFirstAnswers(lost=2)
    answer, calls = call_until_answered(_Executor(), client, None, "the answer", timeout=5.0, every=0.05)
    assert (answer, calls, client.calls) == ("answer to call 3", 3, 3)
    assert call_until_answered(_Executor(), _LosesFirstAnswers(0), None, "the answer", every=0.05) == \
        ("answer to call 1", 1)
    with pytest.raises(AssertionError, match=r"timed out after 0.3 s waiting for the answer \(\d+ calls, none"):
        call_until_answered(_Executor(), _LosesFirstAnswers(10 ** 6), None, "the answer", timeout=0.3, every=0.05)
