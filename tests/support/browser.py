"""The web console in a real browser: Debian's chromium, headless, driven by selenium through the
system chromedriver. Nothing is downloaded: the driver's and the browser's paths are given, so
selenium-manager is never run. Used by tests/operator/test_console.py and
tests/examples/test_farm_console.py."""

from __future__ import annotations

from pathlib import Path

from selenium import webdriver
from selenium.webdriver.chrome.service import Service

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
PAGE_SNAPSHOT = """
const all = (selector) => [...document.querySelectorAll(selector)];
return {
  live: document.getElementById("live").textContent,
  routes: Object.fromEntries(all("#routes tbody tr").map((row) => [row.getAttribute("data-route"),
    Object.fromEntries([...row.cells].map((cell) => [cell.className.split(" ").pop(), cell.textContent]))])),
  dead: all("#dead-letters tbody tr").map((row) => ({route: row.getAttribute("data-route"),
    stage: row.querySelector(".stage").textContent, reason: row.querySelector(".reason").textContent})),
  agents: Object.fromEntries(all("#map circle").map((dot) => [dot.getAttribute("data-agent"),
    [Number(dot.getAttribute("cx")), Number(dot.getAttribute("cy"))]])),
  labels: all("#map text.agent-label").map((text) => text.textContent),
  scale: (document.querySelector("#map text.scale-label") || {textContent: ""}).textContent,
  tap: all("#tap-lines li").map((item) => item.textContent),
  summary: document.getElementById("summary").textContent,
  workers: document.getElementById("workers-panel").hidden ? [] : all("#workers tbody tr").map((row) =>
    Object.fromEntries([...row.cells].map((cell) => [cell.className.split(" ").pop(), cell.textContent]))),
};
"""
"""What the page shows, read in one script (the page redraws every second: elements found one
by one could be replaced between two reads)."""


def browser(profile: Path, window: str = "1400,1000") -> webdriver.Chrome:
    """Headless chromium with the system driver; no network of its own (no updates, sync, QUIC)."""
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--ignore-certificate-errors", f"--window-size={window}",
                 f"--user-data-dir={profile}"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=options)
