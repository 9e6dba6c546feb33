"""Benchmark: the web page's STOP, from the browser's click to the navigation goal CANCELED, beside the
terminal's ``/cancel_command`` (the baseline of bench/decision_maker_cancel.py) in the same run; and
how soon a ``/task_status`` update is drawn on the page.

Runs the simulated nav server, the decision maker and ``web_ui_node`` as real processes on a leased
ROS domain (loopback only), and a headless Chromium on the page, driven over the DevTools protocol.
Trials alternate: a far ``goto`` is sent on ``/manual_command``; once its nav goal is active, either

* **browser**: a real mouse click on the page's STOP (``Input.dispatchMouseEvent``); t0 = just before
  the button is released, when the page's ``click`` fires; or
* **terminal**: ``/cancel_command`` published from this process (what ``cancel_command_node`` does);

then times until the nav server's status says CANCELED (its ``navigate_to_pose/_action/status``,
seen by this process) and until ``/task_status`` says cancelled. For the browser it also prints the
page's own figure: click → the page shows the goal CANCELED (``performance.now()`` in the page).

Status to page: every ``/task_status`` update carries the decision maker's wall-clock ``stamp``; the
page records when it drew it (``Date.now()``, same machine); printed beside the same delay for a plain
rclpy subscriber in this process.

Usage: ``source scripts/env.sh && python bench/web_stop.py [--trials 40]`` (``make bench-web-stop``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
import time

from std_msgs.msg import String

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from action_msgs.msg import GoalStatus  # noqa: E402
from decision_maker_cancel import ENDED, Bench, summary  # noqa: E402

from decision_maker.execution.engine import TaskState  # noqa: E402
from decision_maker.topics import COMMAND_QOS  # noqa: E402
from home_robot_bringup.domain import DomainLease  # noqa: E402
from home_robot_bringup.launcher import apply_overrides  # noqa: E402
from home_robot_bringup.nodeset import load_nodeset  # noqa: E402
from home_robot_bringup.process import Supervisor, node_environment  # noqa: E402
from home_robot_web.cdp import Chromium  # noqa: E402

TARGET_MS = 100.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=40, help="trials in all (half browser, half terminal)")
    opts = ap.parse_args()
    with DomainLease() as lease:
        specs = [s for s in load_nodeset("sim_robot") + load_nodeset("web_ui")
                 if s.name in ("mock_nav_server", "decision_maker", "web_ui")]
        specs = apply_overrides(specs, ["mock_nav_server.speed=0.2", "decision_maker.batch_timeout_s=3600.0",
                                        "web_ui.port=0", "web_ui.messages_per_s=100.0"])
        sup = Supervisor(specs, node_environment(lease.domain_id), echo=None)
        sup.start()
        bench = browser = None
        ros_delay_ms: list[float] = []
        try:
            sup.wait_ready(90.0)
            url = re.search(r"ready: web UI at (\S+)", sup.get("web_ui").output()).group(1)
            bench = Bench(lease.domain_id)

            def on_status(msg: String) -> None:  # the plain subscriber beside the page
                now = time.time()
                stamp = json.loads(msg.data).get("stamp", 0.0)
                if stamp:
                    ros_delay_ms.append((now - stamp) * 1000.0)

            bench.node.create_subscription(String, "task_status", on_status, COMMAND_QOS)
            browser = Chromium()
            page = browser.page(1280, 900)
            page.navigate(url)
            page.wait_for("window.hr && hr.connected && hr.hello > 0", 30)
            deadline = time.monotonic() + 20
            while (bench.cmd.get_subscription_count() == 0 or bench.cancel.get_subscription_count() < 2) \
                    and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)
            to_cancelled: dict[str, list[float]] = {"browser": [], "terminal": []}
            to_task: dict[str, list[float]] = {"browser": [], "terminal": []}
            page_shown: list[float] = []
            known: set[bytes] = set()
            failures = 0
            for i in range(opts.trials):
                goal = bench.start_far_goal(i, known)
                cid = i + 1
                time.sleep(0.05)  # let the goal run for a moment
                via = ("browser", "terminal")[i % 2]
                if via == "browser":
                    t0 = page.click("#stop")
                else:
                    t0 = time.monotonic()
                    bench.cancel.publish(String(data="bench"))
                with bench.cond:
                    done = bench.cond.wait_for(
                        lambda g=goal, c=cid: bench.goal_status[g][0] in ENDED and c in bench.task_final, 10.0)
                    status, t_goal = bench.goal_status[goal]
                    state, t_task = bench.task_final.get(cid, (None, 0.0))
                if not done or status != GoalStatus.STATUS_CANCELED or state is not TaskState.CANCELLED:
                    failures += 1
                    print(f"trial {i} ({via}): done={done} goal status={status} task state={state}")
                    continue
                to_cancelled[via].append((t_goal - t0) * 1000)
                to_task[via].append((t_task - t0) * 1000)
                if via == "browser":
                    page.wait_for("hr.goalCanceledAt !== null", 10)
                    page_shown.append(page.evaluate("hr.goalCanceledAt - hr.stopClickedAt"))
                time.sleep(0.05)
            shown = page.evaluate("hr.statusShown")
        finally:
            if browser is not None:
                browser.close()
            if bench is not None:
                bench.close()
            sup.stop()
    page_delay_ms = [s["shown"] - s["stamp"] * 1000.0 for s in shown if s.get("stamp")]
    print(f"web STOP benchmark ({opts.trials} trials alternating browser / terminal; mock nav server, decision_maker "
          f"and web_ui_node processes, headless Chromium; loopback; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} CPUs)")
    names = {"browser": "browser STOP click", "terminal": "/cancel_command published (terminal path)"}
    for via in ("browser", "terminal"):
        if to_cancelled[via]:
            print(summary(f"{names[via]} -> nav goal CANCELED (server status)", to_cancelled[via]))
            print(summary(f"{names[via]} -> /task_status cancelled", to_task[via]))
    if page_shown:
        print(summary("browser STOP click -> page shows the goal CANCELED (page clock)", page_shown))
    if to_cancelled["browser"] and to_cancelled["terminal"]:
        ratio = statistics.median(to_cancelled["browser"]) / statistics.median(to_cancelled["terminal"])
        print(f"browser / terminal, median to CANCELED: {ratio:.2f}x")
    if page_delay_ms and ros_delay_ms:
        print(summary("/task_status stamp -> drawn on the page (wall clock, 1 ms steps)", page_delay_ms))
        print(summary("/task_status stamp -> received by an rclpy subscriber (baseline)", ros_delay_ms))
    print(f"failed trials (goal not CANCELED / status not cancelled): {failures}")
    for name, ms in (("browser STOP -> nav goal CANCELED", to_cancelled["browser"]),
                     ("/task_status -> drawn on the page", page_delay_ms)):
        if ms:
            under = sum(1 for m in ms if m < TARGET_MS)
            print(f"target {name} under {TARGET_MS:g} ms: {'met' if under == len(ms) else 'NOT met'} in every "
                  f"trial: {under} of {len(ms)} (median {statistics.median(ms):.2f} ms, max {max(ms):.2f} ms)")
    return 0 if failures == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
