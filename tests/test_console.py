"""The browser console (``/console/``, issue 39), end to end in a real headless Chromium.

A real ``eyeserver serve`` on loopback drives the simulated room with an imported and activated
calibration, a patient and a reference captured at set-up; Debian's ``chromium`` (driven by
Playwright from PyPI, never Playwright's own browsers) logs in with a token and uses the console
as a therapist and a physicist would; a second daemon, with the daily QA's lockout on, serves
the QA view and the therapist's lockout banner (one test, a morning's order). Every page is
loaded under the console's Content-Security-Policy, and every console error of the page fails
the test. Screenshots are
written to each test's tmp dir and their paths printed (``pytest -s`` shows them); with
``EYESERVER_SCREENSHOTS=<dir>`` each is also written there as ``console-<name>.png``, reduced to
a 256-colour palette (``bash scripts/console_screenshots.sh`` renews docs/images/ so).

The first tests need no browser: the files are served from the package without a token, ship
everything they load, and ``GET /api/v1/whoami`` tells a client its role.
"""

from __future__ import annotations

import math
import os
import re
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from eyeserver.api.routers.console import CONSOLE_DIR, CONTENT_SECURITY_POLICY
from eyeserver.bench.daemon import DaemonProcess, zip_directory
from tests.apiclient import API, OPERATOR_TOKEN, Client, auth

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
PATIENT = "P-CONSOLE-1"
VIEWPORT = {"width": 1600, "height": 1000}
SACCADE_DEG = 8.0  # the patient's gaze tolerance is 1°
TIMEOUT_MS = 30_000
SCREENSHOTS = os.environ.get("EYESERVER_SCREENSHOTS")
"""Where the views' screenshots are also written for the documentation (unset: nowhere)."""


# --- the files and the caller's role, without a browser ----------------------------------------


def test_the_console_is_served_from_the_package_without_a_token(client: Client) -> None:
    page = client.get("/console/", headers={"Authorization": ""})
    script = client.get("/console/js/main.js", headers={"Authorization": ""})
    bare = client.get("/console", headers={"Authorization": ""})
    home = client.get("/", headers={"Authorization": ""})
    missing = client.get("/console/js/nothing.js")

    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "<title>eyeserver console</title>" in page.text
    assert page.headers["content-security-policy"] == CONTENT_SECURITY_POLICY
    assert page.headers["x-content-type-options"] == "nosniff"
    assert page.headers["cache-control"] == "no-cache"
    # ES modules load only with a JavaScript type.
    assert script.status_code == 200 and "javascript" in script.headers["content-type"]
    assert script.headers["content-security-policy"] == CONTENT_SECURITY_POLICY
    assert bare.status_code == 307 and bare.headers["location"].endswith("/console/")
    assert home.status_code == 307 and home.headers["location"].endswith("/console/")
    assert missing.status_code == 404


def test_everything_the_console_loads_ships_with_it() -> None:
    # No internet in a treatment room: no URL of another host in any file, and every module
    # imported and every file the page names is in the package.
    files = sorted(p for p in CONSOLE_DIR.rglob("*") if p.is_file())
    assert {p.relative_to(CONSOLE_DIR).as_posix() for p in files} >= {
        "index.html", "console.css", "js/main.js", "js/api.js", "js/views/therapist.js"}
    for path in files:
        text = path.read_text(encoding="utf-8")
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}/", text, re.I), path
        assert "localStorage" not in text or path.name == "api.js", path
        assert "document.cookie" not in text, path
        for target in re.findall(r'(?:from|import)\s+"(\.[^"]+)"', text):
            assert (path.parent / target).resolve().is_file(), (path, target)
        for target in re.findall(r'(?:src|href)="([^":#]+)"', text):
            assert (path.parent / target).resolve().is_file(), (path, target)


def test_the_documented_screenshots_are_committed_and_small() -> None:
    # README and the guide show the views as the browser tests saw them (docs/images/, made by
    # scripts/console_screenshots.sh); a renamed view must not leave a broken picture.
    root = Path(__file__).resolve().parent.parent
    shown = {(doc.parent / target).resolve()
             for doc in (root / "README.md", root / "docs" / "guide.md")
             for target in re.findall(r"\]\(((?:docs/)?images/console-[\w-]+\.png)\)",
                                      doc.read_text(encoding="utf-8"))}
    assert len(shown) >= 8
    for image in shown:
        assert image.is_file(), image
        assert image.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert image.stat().st_size < 200_000, image  # 256 colours, deflated


def test_whoami_names_the_caller_and_its_roles(client: Client) -> None:
    operator = client.get(f"{API}/whoami", headers=auth(OPERATOR_TOKEN))
    physicist = client.get(f"{API}/whoami")
    nobody = client.get(f"{API}/whoami", headers={"Authorization": "Bearer not-a-token"})

    assert operator.json() == {"name": "operator", "role": "operator", "roles": ["operator"]}
    assert physicist.json() == {"name": "physicist", "role": "physicist",
                                "roles": ["operator", "physicist"]}
    assert nobody.status_code == 401
    assert nobody.json()["detail"] == ("a valid bearer token is needed (Authorization: Bearer "
                                       "<token>)")
    assert "/api/v1/whoami" in client.get(f"{API}/openapi.json").json()["paths"]


# --- a real daemon and a real browser ----------------------------------------------------------


def _set_up(running: DaemonProcess, caldir: Path) -> None:
    """An active calibration (``caldir``), the patient (right eye, seen by unit left) and a
    reference captured at set-up with the eye at rest."""
    client = running.client
    imported = client.post(f"{API}/calibrations", content=zip_directory(caldir),
                           headers={"content-type": "application/zip"})
    assert imported.status_code == 201, imported.text
    activated = client.post(f"{API}/calibrations/{imported.json()['id']}/activate")
    assert activated.status_code == 200, activated.text
    for method, path, body in [
            ("PUT", f"/patients/{PATIENT}", {"eye": "right", "unit": "left"}),
            ("PUT", "/sim/eye", {"position_mm": [0.0, 0.0, -10.0], "gaze_deg": [0.0, 0.0],
                                 "motion": None}),
            ("POST", f"/patients/{PATIENT}/fractions/1/reference/capture", None)]:
        answer = client.request(method, f"{API}{path}", json=body)
        assert answer.status_code in (200, 201), answer.text


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory,
           calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> Iterator[DaemonProcess]:
    """``eyeserver serve`` on the simulated room with an active calibration, the patient
    (right eye, seen by unit left) and a reference captured at set-up with the eye at rest."""
    _sync_api()  # before the ≈ 40 s calibration: skip at once without a browser
    _, caldir = calibrated_rooms("default")
    work = tmp_path_factory.mktemp("console")
    with DaemonProcess(work / "data", log=work / "serve.log") as running:
        _set_up(running, caldir)
        yield running


@pytest.fixture(scope="module")
def browser(daemon: DaemonProcess) -> Iterator[Any]:
    """Debian's Chromium, headless, driven by Playwright."""
    sync_api = _sync_api()
    with sync_api.sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield launched
        finally:
            launched.close()


def _sync_api() -> Any:
    """Playwright's sync API, or a skip saying what is missing."""
    try:
        from playwright import sync_api
    except ImportError:
        pytest.skip("playwright is not installed (pip install playwright; its own browsers are "
                    "not needed: the tests use Debian's chromium)")
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"chromium not found at {CHROMIUM} (apt-get install chromium)")
    return sync_api


class Console:
    """One browser tab on the console, with everything it logged and requested."""

    def __init__(self, browser: Any, daemon: DaemonProcess, shots: Path) -> None:
        self.context = browser.new_context(viewport=VIEWPORT)
        self.page = self.context.new_page()
        self.page.set_default_timeout(TIMEOUT_MS)
        self.base = daemon.url
        self.shots = shots
        self.errors: list[str] = []
        self.warnings: list[str] = []
        self.requests: list[str] = []
        self.page.on("console", self._console)
        self.page.on("pageerror", lambda error: self.errors.append(f"page error: {error}"))
        self.page.on("request", lambda request: self.requests.append(
            f"{request.method} {request.url}"))
        self.page.goto(f"{self.base}/console/")

    def _console(self, message: Any) -> None:
        # A stream's URL carries its token: never into the test's output.
        text = re.sub(r"token=[^&\s'\"]+", "token=[redacted]",
                      f"{message.text} ({message.location.get('url')})")
        if message.type == "error":
            self.errors.append(text)
        elif message.type == "warning":
            self.warnings.append(text)

    def login(self, token: str) -> None:
        self.page.fill("#login-token", token)
        self.page.click("#login-submit")

    def view(self, name: str) -> None:
        self.page.click(f"#nav-{name}")

    def expect(self, selector: str) -> Any:
        from playwright.sync_api import expect

        return expect(self.page.locator(selector))

    def screenshot(self, name: str) -> Path:
        path = self.shots / f"{name}.png"
        self.page.screenshot(path=str(path), full_page=True)
        print(f"screenshot: {path}")
        if SCREENSHOTS:
            _save_for_docs(path, Path(SCREENSHOTS) / f"console-{name}.png")
        return path

    def storage(self) -> dict[str, Any]:
        """What the page keeps: sessionStorage, localStorage and cookies."""
        stored: dict[str, Any] = self.page.evaluate(
            "() => ({session: {...sessionStorage}, local: {...localStorage}})")
        stored["cookies"] = self.context.cookies()
        return stored

    def close(self) -> None:
        if self.warnings:
            print("console warnings:", *self.warnings, sep="\n  ")
        self.context.close()


def _save_for_docs(shot: Path, target: Path) -> None:
    """A screenshot as a small PNG for the documentation: 256 colours (a flat user interface
    loses nothing to see), deflated as far as PNG goes."""
    from PIL import Image

    target.parent.mkdir(parents=True, exist_ok=True)
    with Image.open(shot) as image:
        palette = image.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT,
                                                dither=Image.Dither.NONE)
        palette.save(target, optimize=True)
    print(f"screenshot for the documentation: {target} ({target.stat().st_size // 1024} kB)")


@pytest.fixture
def console(browser: Any, daemon: DaemonProcess, tmp_path: Path,
            ) -> Iterator[Callable[..., Console]]:
    """Opens browser tabs on the console (closed after the test), of ``daemon`` unless the
    test names another (``console(qa_daemon)``)."""
    opened: list[Console] = []

    def open_tab(on: DaemonProcess | None = None) -> Console:
        tab = Console(browser, on or daemon, tmp_path)
        opened.append(tab)
        return tab

    yield open_tab
    for tab in opened:
        tab.close()


def _http(daemon: DaemonProcess, method: str, path: str, **kwargs: Any) -> Any:
    answer = daemon.client.request(method, f"{API}{path}", **kwargs)
    assert answer.status_code < 300, f"{method} {path}: {answer.status_code} {answer.text}"
    return answer.json() if answer.content else None


def _load_patient(tab: Console) -> None:
    tab.page.fill("#patient-id", PATIENT)
    tab.page.click("#patient-load")
    tab.expect("#reference-details").to_contain_text("Reference of fraction 1")


@pytest.mark.slow
def test_a_bad_token_is_refused_with_the_daemons_reason_and_not_kept(
        console: Callable[[], Console]) -> None:
    tab = console()
    tab.login("not-a-token-of-this-daemon")

    tab.expect("#login-error").to_be_visible()
    tab.expect("#login-error").to_have_text(
        "The daemon refused the token: a valid bearer token is needed (Authorization: Bearer "
        "<token>)")
    tab.expect("#app").to_be_hidden()
    tab.screenshot("login-refused")
    assert tab.storage() == {"session": {}, "local": {}, "cookies": []}
    # The one error logged is the browser's own note of the 401 it was answered.
    assert all("401" in error for error in tab.errors), tab.errors


@pytest.mark.slow
def test_every_view_loads_without_console_errors(console: Callable[[], Console],
                                                 daemon: DaemonProcess) -> None:
    tab = console()
    tab.login(daemon.physicist_token)
    tab.expect("#role").to_have_text("physicist")
    # The token is in this tab's sessionStorage only.
    assert tab.storage() == {"session": {"eyeserver.token": daemon.physicist_token},
                             "local": {}, "cookies": []}
    loaded = {
        "therapist": "#beam-lamp[data-link='up']",
        "qa": "#qa-trends figure.trend",
        "calibration": "#session-stereo",
        "calibrations": "#calibration-list tr[data-calibration]",
        "devices": "#device-list [data-device='S1']",
        "reconstruction": "#capture-list tr[data-capture]",
        "audit": "#audit-table tbody tr",
    }
    for view, ready in loaded.items():
        tab.view(view)
        tab.expect(ready).not_to_have_count(0)
        if view == "therapist":
            _load_patient(tab)
            tab.expect("#reference-capture").to_be_visible()
        if view == "qa":  # this daemon runs without the lockout (qa.required = false)
            tab.expect("#qa-status").to_have_attribute("data-locked", "false")
            tab.expect("#qa-reason").to_contain_text("Not required by the settings")
        tab.page.wait_for_timeout(300)  # late requests of the view would log their errors
        tab.screenshot(f"physicist-{view}")
        assert tab.errors == [], (view, tab.errors)
    tab.expect("#daemon-state").to_have_text("idle")
    tab.expect("#daemon-link").to_have_text("live")


@pytest.mark.slow
def test_the_shown_views_own_link_keeps_what_was_typed(console: Callable[[], Console],
                                                       daemon: DaemonProcess) -> None:
    """The first view is shown without a hash; clicking its own link leaves it as it is (it
    was mounted anew, which wiped a patient typed into it: a CI run lost the loaded patient
    that way when the click's navigation came after the typing)."""
    tab = console()
    tab.login(daemon.physicist_token)
    tab.expect("#beam-lamp").to_be_visible()
    tab.page.fill("#patient-id", PATIENT)
    tab.view("therapist")
    tab.expect("#nav-therapist").to_have_class("active")
    tab.page.wait_for_timeout(300)  # the hash's change is handled after the click returns
    tab.expect("#patient-id").to_have_value(PATIENT)
    _load_patient(tab)
    assert tab.errors == [], tab.errors


@pytest.mark.slow
def test_an_operator_sees_no_physicist_view_or_action(console: Callable[[], Console],
                                                      daemon: DaemonProcess) -> None:
    tab = console()
    tab.login(daemon.operator_token)
    tab.expect("#role").to_have_text("operator")
    _load_patient(tab)

    assert tab.page.locator("#nav a").all_inner_texts() == ["Therapist", "Daily QA"]
    # The therapist at set-up captures the reference (docs/security.md, the role model).
    tab.expect("#reference-capture").to_be_enabled()
    tab.expect("#tracking-start").to_be_enabled()
    tab.screenshot("operator-therapist")
    # A physicist's view reached by its address says why, and asks the daemon nothing.
    asked = len(tab.requests)
    for view in ("calibration", "calibrations", "devices", "reconstruction", "audit"):
        tab.page.goto(f"{tab.base}/console/#/{view}")
        tab.expect("#view-refused").to_have_text(
            "This view needs the physicist role; operator is operator.")
    tab.screenshot("operator-refused")
    physicist_routes = re.compile(r"/api/v1/(audit|calibration-sessions|devices|calibrations)")
    assert [r for r in tab.requests[asked:] if physicist_routes.search(r)] == []
    assert [r for r in tab.requests if physicist_routes.search(r)] == []
    assert tab.errors == []
    denied = [e for e in _http(daemon, "GET", "/audit")["items"] if e["outcome"] == "denied"]
    assert denied == []  # the console never made the daemon refuse the operator


@pytest.mark.slow
def test_a_capture_appears_and_the_verification_gives_its_verdict(
        console: Callable[[], Console], daemon: DaemonProcess) -> None:
    tab = console()
    tab.login(daemon.operator_token)
    _load_patient(tab)
    before = _http(daemon, "GET", "/captures", params={"limit": 1})["items"][0]["id"]
    tab.expect("#camera-images").to_have_attribute("data-capture", before)

    tab.page.click("#capture")
    tab.expect("#camera-images").not_to_have_attribute("data-capture", before,
                                                       timeout=60_000)
    newest = _http(daemon, "GET", "/captures", params={"limit": 1})["items"][0]
    tab.expect("#camera-images").to_have_attribute("data-capture", newest["id"])
    assert newest["unit"] == "left"  # the patient's unit
    images = tab.page.locator("#camera-images img")
    assert images.count() == 2  # unit left's two cameras
    for k in range(2):
        assert images.nth(k).evaluate("img => img.complete && img.naturalWidth") == 640
    tab.expect("#capture-caption").to_contain_text(newest["id"])

    tab.page.click("#verify")
    tab.expect("#verdict").to_have_attribute("data-passed", "true", timeout=120_000)
    tab.expect("#verdict .verdict-word").to_have_text("PASSED")
    tab.screenshot("therapist-capture-and-verdict")
    measured = _http(daemon, "GET", "/pose/measurements",
                     params={"patient_id": PATIENT, "fraction": 1})["items"][0]
    tab.expect("#verdict").to_contain_text(measured["id"])
    assert tab.errors == []


@pytest.mark.slow
def test_the_beam_hold_lamp_follows_a_saccade_of_the_simulated_eye(
        console: Callable[[], Console], daemon: DaemonProcess) -> None:
    # Scenes cannot change while tracking, so the eye's script is set before: at rest for 4 s,
    # then turned 8° (tolerance 1°) and back every 4 s; the lamp must clear at rest and hold
    # with the reason out_of_tolerance while the eye is turned.
    script = []
    for k in range(60):
        start = 4.0 + 8.0 * k
        script += [{"t_s": start, "kind": "saccade", "gaze_deg": [SACCADE_DEG, 0.0],
                    "duration_s": 0.03},
                   {"t_s": start + 4.0, "kind": "saccade", "gaze_deg": [0.0, 0.0],
                    "duration_s": 0.03}]
    _http(daemon, "PUT", "/sim/eye", json={"motion": {
        "drift_deg": 0.02, "saccade_rate_hz": 0.0, "blink_rate_hz": 0.0, "script": script}})
    tab = console()
    tab.login(daemon.operator_token)
    _load_patient(tab)
    lamp = "#beam-lamp"
    tab.expect(lamp).to_have_attribute("data-hold", "true")  # not tracking: held
    tab.expect("#beam-reason").to_have_text("not tracking")
    try:
        tab.page.click("#tracking-start")
        tab.expect("#tracking-stop").to_be_enabled(timeout=120_000)
        # At rest in tolerance: the hold falls after the dwell (a loaded machine misses
        # frames, which holds the beam too; the lamp clears at the first good stretch).
        tab.expect(lamp).to_have_attribute("data-hold", "false", timeout=120_000)
        tab.expect("#beam-lamp .lamp-text").to_have_text("BEAM CLEAR")
        # The tracked unit's live images, renewed a few times a second.
        live = "#camera-images[data-live='true']"
        tab.expect(f"{live} img").to_have_count(2)  # unit left's two cameras
        first = int(tab.page.locator(live).get_attribute("data-frame") or -1)
        tab.expect(live).not_to_have_attribute("data-frame", str(first))
        later = int(tab.page.locator(live).get_attribute("data-frame") or -1)
        assert later > first >= 0
        tab.page.wait_for_function(  # every image decoded, at the camera's size
            "() => [...document.querySelectorAll('#camera-images img')]"
            ".every(img => img.complete && img.naturalWidth === 640)")
        tab.expect("#capture-caption").to_contain_text("Live: unit left")
        tab.screenshot("lamp-clear")
        tab.expect("#beam-reason").to_have_text(re.compile("out_of_tolerance"),
                                                timeout=60_000)
        tab.expect(lamp).to_have_attribute("data-hold", "true")
        gaze = _http(daemon, "GET", "/sim/eye")["eye"]["gaze"]
        turned = math.degrees(math.acos(max(-1.0, min(1.0, gaze[2]))))
        assert turned > SACCADE_DEG / 2, f"the eye is at {turned:.1f}°: held at rest?"
        tab.page.wait_for_timeout(500)  # the plot shows the excursion
        tab.screenshot("lamp-held-saccade")
    finally:
        if _http(daemon, "GET", "/tracking")["running"]:
            tab.page.click("#tracking-stop")
            tab.expect("#tracking-start").to_be_enabled()
        _http(daemon, "PUT", "/sim/eye", json={"gaze_deg": [0.0, 0.0], "motion": None})
    tab.expect("#beam-reason").to_have_text(re.compile("ended|not tracking"))
    tab.expect(lamp).to_have_attribute("data-hold", "true")
    # Stopped: the newest capture's images again, no live ones.
    tab.expect("#camera-images").not_to_have_attribute("data-live", "true")
    tab.expect("#camera-images").to_have_attribute("data-capture", re.compile(".+"))
    previews = [r for r in tab.requests if "/tracking/preview/" in r]
    assert len(previews) >= 4 and all(r.startswith("GET ") for r in previews)
    status = _http(daemon, "GET", "/tracking")
    assert status["running"] is False and status["error"] is None
    assert status["frames_processed"] > 0
    assert tab.errors == []


@pytest.mark.slow
def test_guided_calibration_fills_the_coverage_grid(console: Callable[[], Console],
                                                    daemon: DaemonProcess) -> None:
    tab = console()
    tab.login(daemon.physicist_token)
    tab.view("calibration")
    tab.page.click("#session-stereo")
    tab.expect("#acquire-view").to_be_visible()
    tab.expect("#daemon-state").to_have_text("calibrating")
    covered = tab.page.locator("#coverage .cell[data-covered='true']")
    try:
        counts = []
        for view in range(2):
            tab.page.click("#sim-board")  # the simulated room's board, at the next pose
            tab.expect("#calibration-message").to_contain_text("Board placed")
            tab.page.click("#acquire-view")
            tab.expect("#views tbody tr").to_have_count(view + 1, timeout=60_000)
            tab.expect("#calibration-message").to_contain_text("board found by S1, S2, S3, S4")
            counts.append(covered.count())
        assert 0 < counts[0] < counts[1] < 4 * 16  # four cameras' 4 × 4 cells fill in
        tab.expect("#coverage .coverage-camera").to_have_count(4)
        tab.expect("#missing").to_have_attribute("data-ready", "false")
        tab.expect("#missing li").not_to_have_count(0)
        tab.expect("#missing").to_contain_text("S1: board found in 2 view(s), needs")
        tab.expect("#solve").to_be_disabled()
        tab.screenshot("calibration-coverage")
    finally:
        tab.page.click("#session-close")
    tab.expect("#session-stereo").to_be_visible()
    tab.expect("#daemon-state").to_have_text("idle")
    tab.expect("#calibration-sessions").to_contain_text("closed")
    assert tab.errors == []


@pytest.mark.slow
def test_a_reconstruction_shows_its_height_map_and_turnable_points(
        console: Callable[[], Console], daemon: DaemonProcess) -> None:
    capture = _http(daemon, "GET", "/captures", params={"kind": "measurement",
                                                        "limit": 1})["items"][0]["id"]
    tab = console()
    tab.login(daemon.physicist_token)
    tab.view("reconstruction")
    tab.page.click(f"#capture-list tr[data-capture='{capture}'] button.reconstruct")

    points = tab.page.locator(f"#point-view[data-capture='{capture}']")
    tab.expect(f"#point-view[data-capture='{capture}']").to_have_count(1, timeout=120_000)
    summary = _http(daemon, "GET", f"/captures/{capture}/reconstruction")
    assert int(points.get_attribute("data-points") or 0) > 1000
    tab.expect("#reconstruction-summary dl").to_have_attribute("data-points",
                                                               str(summary["points"]))
    assert tab.page.locator("#height-map").evaluate("img => img.complete && img.naturalWidth") > 0
    before = points.screenshot()
    box = points.bounding_box()
    assert box is not None
    tab.page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    tab.page.mouse.down()
    tab.page.mouse.move(box["x"] + box["width"] / 2 + 120, box["y"] + box["height"] / 2 - 40,
                        steps=5)
    tab.page.mouse.up()
    tab.page.wait_for_timeout(200)
    assert points.screenshot() != before  # the drag turned the cloud
    tab.screenshot("reconstruction")
    assert tab.errors == []


@pytest.mark.slow
def test_device_settings_change_and_a_refusal_shows_the_daemons_reason(
        console: Callable[[], Console], daemon: DaemonProcess) -> None:
    tab = console()
    tab.login(daemon.physicist_token)
    tab.view("devices")
    card = tab.page.locator("#device-list [data-device='S1']")
    exposure = card.locator("input").first

    exposure.fill("50000")  # beyond the simulated camera's 40 ms
    card.locator("button.apply").click()
    tab.expect("#device-list [data-device='S1'] .device-message").to_have_text(
        "S1: exposure_us=50000.0 outside [10.0, 40000.0] (HTTP 422)")
    refused = [e for e in tab.errors if "422" in e]
    tab.errors[:] = [e for e in tab.errors if "422" not in e]  # the browser's note of the 422
    assert len(refused) == 1
    exposure.fill("12000")
    card.locator("button.apply").click()
    tab.expect("#device-list [data-device='S1'] .device-message").to_have_text("Applied.")
    assert _http(daemon, "GET", "/devices/S1")["details"]["exposure_us"] == 12000
    tab.screenshot("devices")
    tab.view("audit")
    tab.expect("#audit-table").to_contain_text("configure_device")
    tab.screenshot("audit")
    _http(daemon, "PATCH", "/devices/S1", json={"exposure_us": 10000})
    assert tab.errors == []


# --- the daily QA: a daemon with the lockout on ------------------------------------------------


@pytest.fixture(scope="module")
def qa_daemon(tmp_path_factory: pytest.TempPathFactory,
              calibrated_rooms: Callable[[str], tuple[Path, Path]]) -> Iterator[DaemonProcess]:
    """``eyeserver serve`` with the daily QA's lockout on (the clinical default; the module's
    other daemon has it off), an active calibration without a QA baseline (so locked), the
    patient and a reference captured at set-up (never locked). Two captures per QA run."""
    _sync_api()
    _, caldir = calibrated_rooms("default")
    work = tmp_path_factory.mktemp("console-qa")
    with DaemonProcess(work / "data", log=work / "serve.log",
                       env={"EYESERVER_QA__REQUIRED": "true",
                            "EYESERVER_QA__FRAMES": "2"}) as running:
        _set_up(running, caldir)
        yield running


@pytest.mark.slow
def test_the_daily_qa_locks_the_therapist_until_a_run_through_the_console_passes(
        console: Callable[..., Console], qa_daemon: DaemonProcess) -> None:
    # One daemon, a morning's order: locked (no QA baseline), what the therapist and the
    # operator see, a physicist's override and its withdrawal, the baseline run through the
    # console (passes, unlocks), the therapist unlocked, the history, trends and report.
    status = _http(qa_daemon, "GET", "/qa/status")
    assert status["locked"] and "has no QA baseline" in status["reason"]

    # The therapist: the banner with the daemon's reason; Verify and Start say why they are off.
    operator = console(qa_daemon)
    operator.login(qa_daemon.operator_token)
    _load_patient(operator)
    operator.expect("#qa-lock").to_be_visible()
    operator.expect("#qa-lock").to_have_attribute("data-kind", "locked")
    operator.expect("#qa-lock-reason").to_have_text(status["reason"])
    operator.expect("#qa-lock a[href='#/qa']").to_have_text("Daily QA")
    for button in ("#verify", "#tracking-start"):
        operator.expect(button).to_be_disabled()
        operator.expect(button).to_have_attribute("title", re.compile("^Locked by the daily "
                                                                      "QA: .*no QA baseline"))
    operator.expect("#reference-capture").to_be_enabled()  # the reference is never locked
    operator.expect("#qa-state").to_have_text("QA locked")
    operator.expect("#beam-lamp").to_have_attribute("data-link", "up")
    operator.screenshot("therapist-qa-locked")

    # The operator may run the QA, but sees no physicist action (baseline, override).
    assert operator.page.locator("#nav a").all_inner_texts() == ["Therapist", "Daily QA"]
    operator.view("qa")
    operator.expect("#qa-status").to_have_attribute("data-locked", "true")
    operator.expect("#qa-reason").to_contain_text(status["reason"])
    operator.expect("#qa-run").to_be_enabled()
    for physicists_only in ("#qa-baseline", "#qa-override-form", "#qa-override-reason",
                            "#qa-override-withdraw"):
        operator.expect(physicists_only).to_have_count(0)
    operator.expect("#qa-trends img").to_have_count(6)

    # A physicist overrides the lockout with a reason, and withdraws it.
    physicist = console(qa_daemon)
    physicist.login(qa_daemon.physicist_token)
    physicist.view("qa")
    physicist.expect("#qa-status").to_have_attribute("data-locked", "true")
    physicist.expect("#qa-override-form").to_be_visible()
    physicist.page.fill("#qa-override-reason", "phantom checked by hand (console test)")
    physicist.page.click("#qa-override")
    physicist.expect("#qa-status").to_have_attribute("data-locked", "false")
    physicist.expect("#qa-override-now").to_contain_text("phantom checked by hand")
    physicist.expect("#qa-override-form").to_be_hidden()
    # The operator's tab hears of it (the qa.override event) and offers no withdrawal.
    operator.expect("#qa-override-now").to_contain_text("phantom checked by hand")
    operator.expect("#qa-override-withdraw").to_have_count(0)
    physicist.page.click("#qa-override-withdraw")
    physicist.expect("#qa-status").to_have_attribute("data-locked", "true")
    physicist.expect("#qa-override-now").to_have_count(0)
    # And of its withdrawal (qa.override_withdrawn): locked again, no override shown.
    operator.expect("#qa-status").to_have_attribute("data-locked", "true")
    operator.expect("#qa-override-now").to_have_count(0)
    overrides = [e for e in _http(qa_daemon, "GET", "/audit")["items"]
                 if e["action"].startswith("qa_override")]
    assert sorted(e["action"] for e in overrides) == ["qa_override", "qa_override_withdrawn"]

    # The baseline run through the console, with the QA phantom placed by its helper.
    physicist.page.click("#sim-phantom")
    physicist.expect("#qa-run-message").to_contain_text("QA phantom placed")
    assert _http(qa_daemon, "GET", "/sim/scene")["kind"] == "eye_phantom_1"
    physicist.page.check("#qa-baseline")
    physicist.page.click("#qa-run")
    physicist.expect("#qa-progress").to_contain_text("Running (as baseline)")
    physicist.expect("#qa-run").to_be_disabled()
    physicist.expect("#qa-result").to_have_attribute("data-passed", "true", timeout=120_000)
    physicist.expect("#qa-progress").to_be_hidden()
    physicist.expect("#qa-result .verdict-word").to_have_text("PASSED")
    figures = physicist.page.locator("#qa-figures tr[data-figure]")
    assert figures.count() == 6
    assert {figures.nth(k).get_attribute("data-passed") for k in range(6)} == {"true"}
    physicist.expect("#qa-status").to_have_attribute("data-locked", "false")
    physicist.expect("#qa-locked-word").to_have_text("NOT LOCKED")
    run = _http(qa_daemon, "GET", "/qa/runs")["items"][0]
    assert run["passed"] and run["baseline"] and run["actor"] == "physicist"
    physicist.expect("#qa-result").to_have_attribute("data-run", run["id"])
    physicist.expect(f"#qa-history tr[data-run='{run['id']}']").to_contain_text("baseline")
    physicist.expect("#qa-trends img").to_have_count(6)
    physicist.page.wait_for_function(  # every trend plot decoded, with the run's point
        "() => [...document.querySelectorAll('#qa-trends img')]"
        ".every(img => img.complete && img.naturalWidth > 0)")
    physicist.expect("#qa-trends").to_contain_text("1 run(s)")
    physicist.screenshot("qa")

    # The printable report of the day, saved as a file (the daemon wants the token).
    with physicist.page.expect_download() as saved:
        physicist.page.click("#qa-report")
    day = _http(qa_daemon, "GET", "/qa/status")["day"]
    assert saved.value.suggested_filename == f"eyeserver-qa-{day}.html"
    report = Path(saved.value.path()).read_text(encoding="utf-8")
    assert f"eyeserver daily QA — {day}" in report and run["id"] in report

    # The therapist is unlocked.
    operator.view("therapist")
    _load_patient(operator)
    operator.expect("#qa-lock").to_be_hidden()
    operator.expect("#verify").to_be_enabled()
    operator.expect("#tracking-start").to_be_enabled()
    operator.expect("#qa-state").to_have_text("QA passed")
    assert operator.errors == [] and physicist.errors == []
    denied = [e for e in _http(qa_daemon, "GET", "/audit")["items"] if e["outcome"] == "denied"]
    assert denied == []  # the console never asked the daemon for what the role may not do
