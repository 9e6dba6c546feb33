"""``demo``: the main job, end to end on the bundled data (``make demo``).

Now: brings up the object database (node set ``object_query``) on the bundled sample map and
asks it, from a second process over real ROS 2, where objects are. Runs on a freshly leased
ROS_DOMAIN_ID with loopback-only discovery; stops every node at the end.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

from home_robot_bringup.domain import DomainLease
from home_robot_bringup.errors import BringupError
from home_robot_bringup.nodeset import find_executable, load_nodeset
from home_robot_bringup.process import Supervisor, node_environment

QUERIES = ("bottle", "Chair", "unicorn")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n")[0])
    ap.add_argument("--ready-timeout", type=float, default=60.0)
    opts = ap.parse_args(argv)
    with DomainLease() as lease:
        env = node_environment(lease.domain_id)
        print(f"demo: ROS_DOMAIN_ID={lease.domain_id}, discovery LOCALHOST", flush=True)
        try:
            sup = Supervisor(load_nodeset("object_query"), env, echo=sys.stdout)
            sup.start()
            sup.wait_ready(opts.ready_timeout)
        except BringupError as exc:
            print(f"demo: error: {exc}", file=sys.stderr)
            return 1
        failures = 0
        try:
            client = find_executable("object_query", "object_query_client", env.get("AMENT_PREFIX_PATH"))
            for name in QUERIES:
                t0 = time.monotonic()
                proc = subprocess.run([client, name, "--timeout", "10"], env=env, capture_output=True, text=True,
                                      timeout=60)
                dt = (time.monotonic() - t0) * 1000
                answer = (proc.stdout + proc.stderr).strip()
                print(f"demo: query {name!r} -> exit {proc.returncode} in {dt:.0f} ms: {answer}", flush=True)
                expected_found = name != "unicorn"
                if (proc.returncode == 0) != expected_found:
                    failures += 1
        finally:
            sup.stop()
        print("demo: " + ("OK — object queries answered over ROS 2 between two processes"
                          if not failures else f"FAILED ({failures} unexpected answers)"), flush=True)
        return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
