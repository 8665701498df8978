"""The live page in headless Chromium (Debian's package, driven by Playwright): a running
job's populations appear on the page, and its numbers are the API's."""

from __future__ import annotations

import os
import shutil

import httpx
import pytest
from conftest import StockCluster, wait_until
from test_http import AUTH, TOKEN, Service, duffing_spec

pytestmark = pytest.mark.browser
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture
def browser():
    if not os.path.exists(CHROMIUM):
        if os.environ.get("CI"):
            pytest.fail("chromium is not installed: `make test` installs Debian's chromium as root")
        pytest.skip("chromium is not installed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
        yield b
        b.close()


def test_live_page_follows_a_running_job(browser, tmp_path):
    cluster = StockCluster(tmp_path / "dask")
    service = Service(tmp_path / "jobs", cluster.address)
    try:
        spec = duffing_spec(max_populations=25, particles=1000)
        job_id = httpx.post(f"{service.url}/jobs", json=spec, headers=AUTH, timeout=60).json()["id"]
        page = browser.new_page(viewport={"width": 1200, "height": 900})
        page.goto(f"{service.url}/jobs/{job_id}/view#token={TOKEN}")
        # populations appear while the job runs
        seen = set()

        def appearing():
            text = page.inner_text("#population")
            if text.isdigit():
                seen.add(int(text))
            return len(seen) >= 3 and page.inner_text("#status") == "running"

        wait_until(appearing, 120, "three populations on the live page")
        page.screenshot(path=str(tmp_path / "running.png"))
        wait_until(lambda: page.inner_text("#status") == "finished", 300, "the job to finish on the page", 0.2)
        wait_until(lambda: page.inner_text("#population") == "25", 10, "the last population on the page")
        wait_until(lambda: "population 25" in page.inner_text("#hists"), 10, "the histograms of the last population")
        page.screenshot(path=str(tmp_path / "finished.png"), full_page=True)
        api = httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()["progress"]
        assert int(page.inner_text("#simulations")) == api["simulations"]
        assert float(page.inner_text("#acceptance")) == pytest.approx(api["acceptance_rate"], abs=5e-4)
        assert float(page.inner_text("#epsilon")) == pytest.approx(api["epsilon"], rel=1e-3)
        leader = max(api["model_probabilities"], key=api["model_probabilities"].get)
        assert page.inner_text("#leader").startswith(leader)
        assert page.locator("#eps path").count() == 1 and page.locator("#probs path").count() == 2
        assert page.locator("#hists svg").count() == len(spec["models"][0 if leader == "cubic" else 1]["priors"])
        index = browser.new_page()
        index.goto(f"{service.url}/#token={TOKEN}")
        wait_until(lambda: job_id[:8] in index.inner_text("#jobs"), 10, "the job on the index page")
        if os.environ.get("ABCNS_SCREENSHOTS"):
            shutil.copy(tmp_path / "finished.png", os.environ["ABCNS_SCREENSHOTS"])
    finally:
        service.close()
        cluster.close()
