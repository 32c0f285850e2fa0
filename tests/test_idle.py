"""`haactl bench idle`: the local measurement covers each host's whole process tree (fork server, agents)."""

import os
import subprocess
import sys

from haa.lab.experiments.idle import _proc_cpu, _tree_cpu

BURN = (
    "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.4: pass\n"
    "print('done', flush=True)\ntime.sleep(30)"
)


def test_tree_counts_the_cpu_and_memory_of_children():
    me = {"x": os.getpid()}
    before_tree, before_own = _tree_cpu(me)["x"][0], _proc_cpu(me)["x"][0]
    child = subprocess.Popen([sys.executable, "-c", BURN], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == "done"
        tree_cpu, tree_pss = _tree_cpu(me)["x"]
        own_cpu = _proc_cpu(me)["x"][0]
        assert tree_cpu - before_tree >= 0.35  # the child's 0.4 s of CPU
        assert own_cpu - before_own < 0.2  # not ours
        assert tree_pss > 0
    finally:
        child.kill()
        child.wait()  # reaped: the pid names no process now
    assert _tree_cpu({"gone": child.pid}) == {}  # a vanished process is skipped, not an error
