"""Screenshot of the web page for the README (docs/img/web_ui.png): the demo's node set, a headless
Chromium, and a person's short session — "give me the bottle", "where is the bottle", then "clean
table" stopped with STOP half-way.

Usage: ``source scripts/env.sh && python scripts/web_ui_screenshot.py [docs/img/web_ui.png] [--phone PATH]``
"""

from __future__ import annotations

import argparse
import json
import re

from home_robot_bringup.domain import DomainLease
from home_robot_bringup.launcher import apply_overrides
from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.process import Supervisor, node_environment
from home_robot_web.cdp import Chromium, Page

TASK = ("([...document.querySelectorAll('#tasks > li')]"
        ".find(li => li.querySelector('.text').textContent === {}) || {{}})")


def say(page: Page, text: str) -> None:
    page.type("#cmd", text)
    page.press_enter()


def state_of(text: str) -> str:
    return TASK.format(json.dumps(text)) + ".dataset?.state"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("path", nargs="?", default="docs/img/web_ui.png")
    ap.add_argument("--phone", default="", help="also a phone-sized screenshot here")
    opts = ap.parse_args()
    with DomainLease() as lease:
        sup = Supervisor(apply_overrides(load_nodeset("demo"), ["web_ui.port=0"]),
                         node_environment(lease.domain_id), echo=None)
        sup.start()
        try:
            sup.wait_ready(90.0)
            url = re.search(r"ready: web UI at (\S+)", sup.get("web_ui").output()).group(1)
            with Chromium() as browser:
                page = browser.page(1280, 900)
                page.navigate(url)
                page.wait_for("hr.connected && hr.hello > 0 && /map points/.test($('mapinfo').textContent)", 30)
                say(page, "give me the bottle")
                page.wait_for(f"{state_of('give me the bottle')} === 'succeeded'", 120)
                say(page, "where is the bottle")
                page.wait_for(f"{state_of('where is the bottle')} === 'succeeded'", 30)
                say(page, "clean table")
                moving = "['accepted', 'executing'].includes(document.querySelector('#goal').dataset.status)"
                page.wait_for(f"{TASK.format(json.dumps('clean table'))}.querySelectorAll?.('.steps li').length >= 2"
                              f" && {moving}", 60)
                page.click("#stop")
                page.wait_for(f"{state_of('clean table')} === 'cancelled'", 30)
                page.wait_for("hr.goalCanceledAt !== null", 10)
                page.screenshot(opts.path)
                print(f"wrote {opts.path}")
                if opts.phone:
                    phone = browser.page(390, 844, mobile=True)
                    phone.navigate(url)
                    phone.wait_for("hr.connected && hr.hello > 0 && /map points/.test($('mapinfo').textContent)", 30)
                    phone.screenshot(opts.phone)
                    print(f"wrote {opts.phone}")
        finally:
            sup.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
