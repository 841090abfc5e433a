"""colonyd.priority: the alone replays' priority, relative to the run's own."""

from __future__ import annotations

import json

from tests.shared import fresh_process

#: In a process at niceness +4 (a demo started under `nice`): a child lowered by 10, then given
#: "our" priority back.
CODE = """
import json, os, subprocess
os.nice(4)
from colonyd.priority import as_us, below_us
child = subprocess.Popen(["sleep", "30"])
try:
    below_us(child.pid)
    lowered = os.getpriority(os.PRIO_PROCESS, child.pid)
    as_us(child.pid)
    back = os.getpriority(os.PRIO_PROCESS, child.pid)
finally:
    child.kill()
    child.wait()
print(json.dumps([os.getpriority(os.PRIO_PROCESS, 0), lowered, back]))
"""


def test_replay_priority_is_relative_to_the_run() -> None:
    """The demo's replays were set to niceness 10 and then 0, whatever the demo's own: run under
    `nice -n 15` as root, they ran above the demo that started them."""
    own, lowered, back = json.loads(fresh_process(CODE).strip().splitlines()[-1])
    assert lowered == min(19, own + 10)
    assert back >= own  # never above the run's priority
    assert back in (own, lowered)  # ours again where permitted (root), else left lowered
