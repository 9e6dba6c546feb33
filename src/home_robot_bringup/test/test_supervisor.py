"""The process supervisor on small real programs (no ROS): readiness, prefixes, deaths, stop escalation."""

import io
import os
import signal
import sys
import textwrap
import time

import pytest

from home_robot_bringup.domain import DomainLease
from home_robot_bringup.errors import NodeNotReady
from home_robot_bringup.nodeset import NodeSpec
from home_robot_bringup.process import Supervisor, node_environment


@pytest.fixture
def prefix(tmp_path):
    """An install prefix with small programs in the ros2-run layout: <prefix>/lib/demo/<exe>."""
    lib = tmp_path / "lib" / "demo"
    lib.mkdir(parents=True)
    programs = {
        "ready_then_wait": """
            import signal, sys, time
            # the handler before "ready:": a SIGINT right after it must not hit the default handler
            signal.signal(signal.SIGINT, lambda *a: (print("bye", flush=True), sys.exit(0)))
            print("starting", flush=True); time.sleep(0.2); print("ready: serving", flush=True)
            while True: time.sleep(0.05)
        """,
        "stubborn": """
            import signal, time
            signal.signal(signal.SIGINT, signal.SIG_IGN); signal.signal(signal.SIGTERM, signal.SIG_IGN)
            print("ready: ignoring signals", flush=True)
            while True: time.sleep(0.05)
        """,
        "crash_at_start": """
            import sys
            print("cannot load map: map_path='/nope'", flush=True); sys.exit(2)
        """,
        "die_later": """
            import sys, time
            print("ready: for a moment", flush=True); time.sleep(0.5); sys.exit(3)
        """,
        "print_env": """
            import os, sys
            print("ready:", os.environ["ROS_DOMAIN_ID"], os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"], sys.argv[1:],
                  flush=True)
            import time; time.sleep(30)
        """,
    }
    for name, body in programs.items():
        path = lib / name
        path.write_text(f"#!{sys.executable}\n" + textwrap.dedent(body))
        path.chmod(0o755)
    return str(tmp_path)


def env_for(prefix: str, domain: int = 77) -> dict[str, str]:
    return node_environment(domain, {**os.environ, "AMENT_PREFIX_PATH": prefix})


def spec(name: str, exe: str, ready: str | None = "ready:", **kw) -> NodeSpec:
    return NodeSpec(name=name, package="demo", executable=exe, ready=ready, **kw)


def test_ready_prefix_and_clean_sigint_stop(prefix):
    out = io.StringIO()
    sup = Supervisor([spec("alpha", "ready_then_wait"), spec("beta", "ready_then_wait")], env_for(prefix), echo=out,
                     colour=False)
    with sup:
        sup.wait_ready(20)
    assert [p.returncode() for p in sup.processes] == [0, 0]
    lines = out.getvalue().splitlines()
    assert "[alpha] ready: serving" in lines and "[beta] ready: serving" in lines
    assert "[alpha] bye" in lines


def test_coloured_prefixes(prefix):
    out = io.StringIO()
    with Supervisor([spec("alpha", "ready_then_wait")], env_for(prefix), echo=out, colour=True) as sup:
        sup.wait_ready(20)
    assert "\033[36m[alpha]\033[0m ready: serving" in out.getvalue()


def test_environment_and_arguments_reach_the_node(prefix):
    s = spec("gamma", "print_env", parameters={"speed": 2})
    with Supervisor([s], env_for(prefix, domain=55), echo=None) as sup:
        sup.wait_ready(20)
        out = sup.get("gamma").output()
    assert "ready: 55 LOCALHOST" in out
    assert "'__node:=gamma'" in out and "'speed:=2'" in out


def test_escalates_to_sigkill_when_signals_are_ignored(prefix):
    sup = Supervisor([spec("stubborn", "stubborn")], env_for(prefix), echo=None)
    sup.start()
    sup.wait_ready(20)
    t0 = time.monotonic()
    sup.stop(grace=0.5)
    assert sup.get("stubborn").returncode() == -signal.SIGKILL
    assert time.monotonic() - t0 < 10  # bounded by the grace periods, not by the child


def test_death_while_starting_is_reported_with_output(prefix):
    sup = Supervisor([spec("crashy", "crash_at_start")], env_for(prefix), echo=None)
    sup.start()
    with pytest.raises(NodeNotReady, match=r"crashy exited with code 2 while starting:\n.*map_path='/nope'"):
        sup.wait_ready(20)
    sup.stop()


def test_not_ready_before_deadline(prefix):
    sup = Supervisor([spec("silent", "ready_then_wait", ready="never printed")], env_for(prefix), echo=None)
    sup.start()
    with pytest.raises(NodeNotReady, match="silent not ready after"):
        sup.wait_ready(1.0)
    sup.stop()


def test_one_death_stops_all_and_returns_its_code(prefix):
    sup = Supervisor([spec("steady", "ready_then_wait"), spec("mortal", "die_later")], env_for(prefix), echo=None)
    sup.start()
    sup.wait_ready(20)
    assert sup.wait() == 3
    assert sup.get("steady").returncode() == 0  # stopped cleanly by SIGINT, not left running


def test_domain_leases_are_unique_and_released(tmp_path):
    leases = [DomainLease(str(tmp_path)) for _ in range(10)]
    ids = [lease.domain_id for lease in leases]
    assert len(set(ids)) == 10 and all(1 <= i <= 100 for i in ids)
    leases[0].release()
    again = [DomainLease(str(tmp_path)) for _ in range(91)]  # 90 left + the released one
    assert ids[0] in {lease.domain_id for lease in again}
    with pytest.raises(RuntimeError, match="no free ROS_DOMAIN_ID"):
        DomainLease(str(tmp_path))
