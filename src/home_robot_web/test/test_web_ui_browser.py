"""The web page in a real headless Chromium against the whole simulated robot (real processes, real DDS).

One node set (``demo``: the simulated robot and ``web_ui_node`` on a free loopback port) and one
browser are shared by the tests of this module (pytest-xdist may start them afresh between two tests: each test
makes what it needs itself), which run in order as a person would use the page:
a command with its steps and "Done", a question answered in place, STOP during a long task, bad
input, a closed tab, a phone-sized screen. The exposed node (a pairing token on every request) is
started on its own and opened in a new tab of the same browser, its cookies cleared before and after.
"""

from __future__ import annotations

import json
import os
import re
import urllib.error
import urllib.request

import pytest

from home_robot_bringup.domain import DomainLease
from home_robot_bringup.launcher import apply_overrides
from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.process import Supervisor, node_environment
from home_robot_web.cdp import Chromium, chromium_path

# one worker runs the module's tests in order on one node set (make test: pytest -n 2 --dist loadgroup)
pytestmark = [pytest.mark.ros, pytest.mark.xdist_group("web_ui_browser"),
              pytest.mark.skipif(chromium_path() is None, reason="needs chromium (apt-get install chromium)")]

#: the page's task entry of the command with this text, and its state
TASK = "[...document.querySelectorAll('#tasks > li')].find(li => li.querySelector('.text').textContent === {text})"


def task(text: str) -> str:
    return TASK.format(text=json.dumps(text))


def url_of(sup: Supervisor, name: str = "web_ui") -> str:
    m = re.search(r"ready: web UI at (\S+)", sup.get(name).output())
    assert m, sup.get(name).output()
    return m.group(1)


@pytest.fixture(scope="module")
def robot_page():
    """The demo's node set and one browser tab on its page, shared by the module's tests."""
    with DomainLease() as lease:
        specs = apply_overrides(load_nodeset("demo"), ["web_ui.port=0", "mock_nav_server.speed=1.5"])
        sup = Supervisor(specs, node_environment(lease.domain_id), echo=None)
        sup.start()
        browser = None
        try:
            sup.wait_ready(90.0)
            url = url_of(sup)
            browser = Chromium()
            page = browser.page(1280, 900)
            page.navigate(url)
            page.wait_for("window.hr && hr.connected && hr.hello > 0", 30)
            yield sup, browser, page, url
        except BaseException:
            print(sup.output())
            raise
        finally:
            if browser is not None:
                browser.close()
            sup.stop()


def send_command(page, text: str) -> None:
    page.type("#cmd", text)
    page.press_enter()


def test_command_shows_its_steps_and_done(robot_page):
    sup, _, page, _ = robot_page
    send_command(page, "give me the bottle")
    page.wait_for(f"({task('give me the bottle')} || {{}}).dataset?.state === 'succeeded'", 120)
    steps = page.evaluate(f"[...{task('give me the bottle')}.querySelectorAll('.steps li')].map(e => e.textContent)")
    assert len(steps) >= 3 and any("grasp" in s for s in steps) and any("place" in s for s in steps), steps
    assert page.evaluate("hr.acks[0].accepted && hr.acks[0].id > 0 && hr.acks[0].via === 'service'")
    assert page.evaluate(f"{task('give me the bottle')}.querySelector('.sentence').textContent") == "Done."
    assert page.text("#answer") == "Done."  # the answer to the page's own command, under the box
    assert page.evaluate("document.querySelectorAll('#objects tbody tr').length") >= 3  # the object memory
    assert page.evaluate("document.querySelector('#mapinfo').textContent").endswith("map points")


def test_where_is_answered_in_place(robot_page):
    sup, _, page, _ = robot_page
    delivered = f"({task('give me the bottle')} || {{}}).dataset?.state === 'succeeded'"
    if not page.evaluate(delivered):  # this node set was started for this test (pytest-xdist does that when other
        # modules' tests ran on this worker in between): the bottle is given here first
        send_command(page, "give me the bottle")
        page.wait_for(delivered, 120)
    send_command(page, "where is the bottle")
    answer = page.wait_for("(() => { const a = document.querySelector('#answer').textContent;"
                           " return /bottle/i.test(a) && a; })()", 30)
    logs = "".join(f"\n----- {n}\n{sup.get(n).output()[-4000:]}" for n in ("decision_maker", "object_query_server"))
    assert "with you" in answer, answer + logs  # the bottle the first test gave to the user


def test_stop_during_a_long_task_cancels_it(robot_page):
    sup, _, page, _ = robot_page
    send_command(page, "goto:5.0,4.5,0; goto:0.5,0.5,0")
    page.wait_for("['accepted', 'executing'].includes(document.querySelector('#goal').dataset.status)", 30)
    page.click("#stop")
    page.wait_for("document.querySelector('#goal').dataset.status === 'canceled'", 20)
    page.wait_for(f"{task('goto:5.0,4.5,0; goto:0.5,0.5,0')}.dataset.state === 'cancelled'", 20)
    assert "CANCELED" in page.text("#stopinfo") or "Cancelled" in page.text("#stopinfo"), page.text("#stopinfo")
    assert "STOP from the web page" in sup.get("web_ui").output()


def test_bad_input_gets_clear_errors_and_loses_nothing(robot_page):
    sup, _, page, _ = robot_page
    page.evaluate("hr.send('{not json')")
    page.wait_for("hr.errors.some(e => e.startsWith('not JSON'))", 10)
    page.evaluate("hr.send(JSON.stringify({type: 'command', text: 'x'.repeat(20000)}))")  # over 4096 bytes
    page.wait_for("hr.errors.some(e => e.includes('message too large'))", 10)
    page.evaluate("hr.send('y'.repeat(200000))")  # over the websocket limit: the connection is reset
    page.wait_for("hr.errors.some(e => e.includes('connection was reset'))", 10)
    page.wait_for("hr.connected", 20)  # the page reconnected: the node lives
    assert sup.get("web_ui").returncode() is None
    page.type("#cmd", "")
    page.click("#send")
    page.wait_for("hr.errors.some(e => e.startsWith('empty command'))", 10)
    long_text = "please " * 80  # 560 characters: over the 500 the robot takes
    page.evaluate(f"hr.send(JSON.stringify({{type: 'command', text: {json.dumps(long_text)}, ref: 999}}))")
    page.wait_for("hr.errors.some(e => e.startsWith('command too long'))", 10)
    send_command(page, "go home")  # and the page still commands the robot
    page.wait_for(f"({task('go home')} || {{}}).dataset?.state === 'succeeded'", 60)


def test_a_closed_tab_changes_nothing_on_the_robot(robot_page):
    _, browser, page, url = robot_page
    other = browser.page(800, 600)
    other.navigate(url)
    other.wait_for("hr.connected && hr.hello > 0", 30)
    send_command(other, "goto:2.0,1.0,0")
    other.wait_for("hr.acks.length > 0", 10)
    browser.close_page(other)
    page.wait_for(f"({task('goto:2.0,1.0,0')} || {{}}).dataset?.state === 'succeeded'", 60)


def test_phone_sized_viewport(robot_page):
    _, browser, _, url = robot_page
    phone = browser.page(390, 844, mobile=True)
    try:
        phone.navigate(url)
        phone.wait_for("hr.connected && hr.hello > 0", 30)
        layout = phone.evaluate("(() => { const s = document.querySelector('#stop').getBoundingClientRect();"
                                " return {scroll: document.documentElement.scrollWidth, stopW: s.width,"
                                " stopH: s.height, stopTop: s.top}; })()")
        assert layout["scroll"] <= 390, layout  # nothing wider than the phone
        assert layout["stopW"] >= 300 and layout["stopH"] >= 60 and layout["stopTop"] < 200, layout  # big, on top
    finally:
        browser.close_page(phone)


def test_exposed_page_needs_the_token(robot_page, tmp_path):
    """Its own node set (an exposed web_ui); the module's browser, in a new tab with no cookies."""
    _, browser, _, _ = robot_page
    token = "pairing-token-of-the-test-1234"
    token_file = tmp_path / "token"
    fd = os.open(token_file, os.O_WRONLY | os.O_CREAT, 0o600)
    os.write(fd, token.encode())
    os.close(fd)
    with DomainLease() as lease:
        specs = apply_overrides(load_nodeset("web_ui"), [
            "web_ui.expose=true", "web_ui.bind_address=127.0.0.1", "web_ui.port=0", f"web_ui.token_file={token_file}",
            "web_ui.max_failures=3"])
        sup = Supervisor(specs, node_environment(lease.domain_id), echo=None)
        sup.start()
        try:
            sup.wait_ready(60.0)
            url = url_of(sup)
            assert "pairing token required" in sup.get("web_ui").output() and token not in sup.get("web_ui").output()
            for suffix, code in (("", 401), ("state", 401), ("?token=wrong-token", 403)):
                with pytest.raises(urllib.error.HTTPError) as info:
                    urllib.request.urlopen(url + suffix, timeout=10)
                assert info.value.code == code
            page = browser.page()
            try:
                page.call("Network.clearBrowserCookies")  # cookies are per host, not per port: start with none
                page.navigate(url)  # no token: refused, the browser shows why
                assert "pairing token required" in page.evaluate("document.body.innerText")
                page.navigate(url + "?token=" + token)
                page.wait_for("hr.connected && hr.hello > 0", 30)
                assert page.evaluate("location.search") == ""  # the token left the address bar
                page.navigate(url)  # a reload: the cookie is the key now
                page.wait_for("hr.connected && hr.hello > 0", 30)
            finally:
                page.call("Network.clearBrowserCookies")  # the token's cookie stays with this test
                browser.close_page(page)
            for _ in range(2):  # 3 wrong tokens in all: locked out, even with the right one
                with pytest.raises(urllib.error.HTTPError):
                    urllib.request.urlopen(url + "?token=wrong-again", timeout=10)
            with pytest.raises(urllib.error.HTTPError) as info:
                urllib.request.urlopen(url + "?token=" + token, timeout=10)
            assert info.value.code == 429
            out = sup.get("web_ui").output()
            assert out.count("refused 127.0.0.1") >= 5 and token not in out
        except BaseException:
            print(sup.output())
            raise
        finally:
            sup.stop()


def test_exposed_without_a_token_file_prints_a_new_token_once(launch_nodes):
    sup = launch_nodes(nodeset="web_ui", set=["web_ui.expose=true", "web_ui.bind_address=127.0.0.1", "web_ui.port=0"])
    out = sup.get("web_ui").output()
    printed = re.findall(r"pairing token \(shown once\): (\S+) — open (\S+)", out)
    assert len(printed) == 1, out
    token, link = printed[0]
    with urllib.request.urlopen(link, timeout=10) as r:  # the printed link opens the page
        assert r.status == 200 and b"Home robot" in r.read()
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(url_of(sup), timeout=10)
    assert info.value.code == 401
    assert sup.get("web_ui").output().count(token) == 2  # the one printed line (token and link), nowhere else
