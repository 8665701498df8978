"""The live page in headless Chromium (Debian's package, driven by Playwright): a running
job's populations appear on the page, its numbers are the API's, and what a person sees is
drawn: the marginals' bars (with heights), the charts' axes with their labels and units,
each model in its `abcns plot` colour, the workers now."""

from __future__ import annotations

import json
import os
import re
import shutil

import httpx
import pytest

from benchmarks.harness import AUTH, TOKEN, Service, duffing_spec, wait_until

pytestmark = pytest.mark.browser
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def chromium():
    if not os.path.exists(CHROMIUM):
        if os.environ.get("CI"):
            pytest.fail("chromium is not installed: `make test` installs Debian's chromium as root")
        pytest.skip("chromium is not installed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
        yield b
        b.close()


@pytest.fixture
def browser(chromium):
    """One Chromium for the module; each page a test opens (``new_page``: a browser context
    of its own, so nothing of one test's pages reaches another's) is closed after the test."""
    before = set(chromium.contexts)
    yield chromium
    for context in chromium.contexts:
        if context not in before:
            context.close()


@pytest.fixture(scope="module")
def service(cluster, tmp_path_factory):
    """One service for the module (its index page lists only this module's jobs), on the
    run's shared cluster (2 workers): each test runs its own jobs on it, one at a time."""
    service = Service(tmp_path_factory.mktemp("browser") / "jobs", cluster.address)
    yield service
    service.close()


def read_all(page, selector: str, read: str) -> list:
    """``read`` (a JavaScript function of an element) of every element ``selector`` matches,
    queried and read in one evaluation, one task of the page's script. The live page
    replaces its charts, bars and legend as events come: a query and a read in two steps
    (``eval_on_selector_all``, ``locator.all_text_contents``) can read elements replaced in
    between (detached: no computed style, a box of zero height)."""
    return page.evaluate(f"() => Array.from(document.querySelectorAll({json.dumps(selector)}), {read})")


def drawn_bars(page) -> int:
    """The marginals' bars a person sees: <rect> elements drawn with a height on screen."""
    return sum(h > 0 for h in read_all(page, "#hists svg rect", "r => r.getBoundingClientRect().height"))


def marginals(page) -> tuple[int, int, int]:
    """The marginals' charts, their bars and the bars drawn with a height, read at once (the
    leading model, and with it the number of charts, may change with the next population)."""
    return tuple(page.evaluate("""() => {
        const charts = document.querySelectorAll("#hists svg"), bars = document.querySelectorAll("#hists svg rect");
        return [charts.length, bars.length, Array.from(bars).filter(r => r.getBoundingClientRect().height > 0).length];
    }"""))


def rgb(hex_colour: str) -> str:
    return "rgb({}, {}, {})".format(*(int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)))


def test_live_page_follows_a_running_job(browser, service, tmp_path):
    """A job far longer than the checks (400 populations), cancelled once the running page
    has been checked, so it is running while it is looked at on any machine."""
    spec = duffing_spec(max_populations=400, particles=500, noise_floor=False)  # runs until cancelled
    job_id = httpx.post(f"{service.url}/jobs", json=spec, headers=AUTH, timeout=60).json()["id"]
    try:
        page = browser.new_page(viewport={"width": 1200, "height": 900})
        page.goto(f"{service.url}/jobs/{job_id}/view#token={TOKEN}")
        # populations appear while the job runs, and so do the marginals' bars
        seen = set()

        def appearing():
            text = page.inner_text("#population")
            if text.isdigit():
                seen.add(int(text))
            return len(seen) >= 3 and page.inner_text("#status") == "running" and drawn_bars(page) > 0

        wait_until(appearing, 120, "three populations and the marginals' bars on the live page")
        page.screenshot(path=str(tmp_path / "running.png"))
        n_params, n_bars, n_drawn = marginals(page)
        assert n_bars == 20 * n_params and n_drawn >= 2 * n_params, (n_params, n_bars, n_drawn)
        # the charts are labelled along their axes: titles, and tick values on both axes
        for chart, ylabel in (("#eps", "tolerance \u03b5 (%)"), ("#acc", "acceptance rate"), ("#probs", "model probability")):
            titles = read_all(page, f"{chart} text.axis-title", "t => t.textContent")
            assert titles == ["population", ylabel], (chart, titles)
            assert page.locator(f"{chart} text.lbl").count() >= 4, chart
        assert page.inner_text("#eps-unit").strip() == "%"
        # each model in its abcns plot colour, and the cluster's workers
        from service.report.colours import model_colour

        colours = read_all(page, "#legend .model", "s => getComputedStyle(s).color")
        assert colours == [rgb(model_colour(i)) for i in range(len(spec["models"]))]
        wait_until(lambda: page.inner_text("#workers") == "2", 10, "the workers on the page")
        # where the job's loop runs: the worker of its placement (GET /jobs/{id}), as words
        worker = httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()["placement"]["worker"]
        assert re.fullmatch(rf"(whole on|spread from) {re.escape(worker)}", page.inner_text("#placement")), \
            page.inner_text("#placement")
        # and the cluster's share of time on the jobs' simulations (/health), as a percentage
        wait_until(lambda: re.fullmatch(r"[1-9]\d* %", page.inner_text("#utilization")), 30, "the utilization on the page")
        assert int(page.inner_text("#utilization").split()[0]) <= 100, page.inner_text("#utilization")
        # ended: the page shows the last population, its numbers are the API's
        assert httpx.delete(f"{service.url}/jobs/{job_id}", headers=AUTH, timeout=60).status_code == 202
        wait_until(lambda: page.inner_text("#status") == "cancelled", 300, "the job to end on the page", 0.2)
        info = httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()
        api, last = info["progress"], str(info["progress"]["population"])
        wait_until(lambda: page.inner_text("#population") == last, 10, "the last population on the page")
        wait_until(lambda: re.search(rf"population {last}\b", page.inner_text("#hists")), 10,
                   "the histograms of the last population")
        page.screenshot(path=str(tmp_path / "ended.png"), full_page=True)
        n_params, _, n_drawn = marginals(page)
        assert n_drawn >= 2 * n_params
        assert int(page.inner_text("#simulations")) == api["simulations"]
        assert float(page.inner_text("#acceptance")) == pytest.approx(api["acceptance_rate"], abs=5e-4)
        assert float(page.inner_text("#epsilon")) == pytest.approx(api["epsilon"], rel=1e-3)
        probs = api["model_probabilities"]
        probs = [probs[m] for m in info["models"]] if isinstance(probs, dict) else probs  # a list, or name -> value
        leader = info["models"][probs.index(max(probs))]
        assert page.inner_text("#leader").startswith(leader)
        assert page.locator("#eps path").count() == 1 and page.locator("#probs path").count() == 2
        lead = spec["models"][[m["name"] for m in spec["models"]].index(leader)]
        assert read_all(page, ".hist text.axis-title", "t => t.textContent") == list(lead["priors"])  # each chart's parameter
        index = browser.new_page()
        index.goto(f"{service.url}/#token={TOKEN}")
        wait_until(lambda: job_id[:8] in index.inner_text("#jobs"), 10, "the job on the index page")
        if os.environ.get("ABCNS_SCREENSHOTS"):
            shutil.copy(tmp_path / "running.png", os.environ["ABCNS_SCREENSHOTS"])
    finally:  # the service runs one job at a time: never leave this one running for the next test
        httpx.delete(f"{service.url}/jobs/{job_id}", headers=AUTH, timeout=60)


def test_the_page_says_when_a_run_is_undecided(browser, service):
    """Paper §4.1 with the paper's variant, seed 2: the run stops at the cubic model's best
    fit (eps 7.874) with both models above 0.1 (measured: benchmarks.model_selection
    --variant paper). The summary warns, and the page shows the same warning once it ends."""
    spec = duffing_spec(max_populations=120, particles=1000)
    spec["sampler"]["variant"] = "paper"
    spec["sampler"].pop("batch_size")  # the example's own random stream, as the benchmark ran it
    spec["stop"] = {"min_epsilon_decrease": 1e-7, "max_populations": 120}
    spec["seed"] = 2
    job_id = httpx.post(f"{service.url}/jobs", json=spec, headers=AUTH, timeout=60).json()["id"]
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    page.goto(f"{service.url}/jobs/{job_id}/view#token={TOKEN}")
    wait_until(lambda: page.inner_text("#status") == "finished", 600, "the job to finish on the page", 0.5)
    result = httpx.get(f"{service.url}/jobs/{job_id}/result", headers=AUTH, timeout=60).json()
    assert any(w.startswith("undecided") for w in result["warnings"]), result["warnings"]
    # held at the cubic's best fit (7.8738: `abcns run` of this spec ends at 7.873769639508209, and
    # since the spec reaches the worker typed, with the stop rules it named, so does the service)
    assert 7.873 <= result["epsilon"][-1] < 7.95
    wait_until(lambda: "warning: undecided" in page.inner_text("#warnings"), 30, "the warning on the page")
    # a finished job's page draws the last population's marginals
    last = str(len(result["epsilon"]))
    wait_until(lambda: re.search(rf"population {last}\b", page.inner_text("#hists")), 10,
               "the histograms of the last population")
    n_params, _, n_drawn = marginals(page)
    assert n_drawn >= 2 * n_params > 0


def fulfil_from(answers: dict, route, path: str) -> None:
    """Fulfil a routed request of the page from ``answers`` (path -> (content type, body)),
    with the service's content security policy; 404 for any other path."""
    from service.http.page import CSP

    if path in answers:
        kind, body = answers[path]
        route.fulfill(status=200, content_type=kind, body=body, headers={"Content-Security-Policy": CSP})
    else:
        route.fulfill(status=404, body="")


def test_the_page_says_where_the_answer_is_read_and_marks_the_floor(browser):
    """Issue T: the page says at which population and tolerance the answer (the leading
    model) is read, and marks the noise floor and the decision tolerance on the tolerance
    chart and the decision population on the model-probability chart. The page is served
    as the service serves it (its HTML and Content-Security-Policy) by Playwright's routing,
    with five population events (tolerance 10 / t; a floor from population 2: 2.8, decision
    3.2), so population 3 (3.333) holds the answer, linear 0.9, though the last says cubic."""
    from service.http.page import VIEW

    origin, job = "http://abcns.test", "0123456789abcdef"
    events = []
    for t in range(1, 6):
        floor = (None, None) if t == 1 else (2.8, 3.2)
        events.append(("population", {"population": t, "epsilon": 10.0 / t, "epsilon_next": 10.0 / (t + 1),
                                      "acceptance_rate": 0.5, "simulations": 1000 * t, "elapsed_s": float(t),
                                      "model_probabilities": {"linear": 0.9 if t <= 3 else 0.1,
                                                              "cubic": 0.1 if t <= 3 else 0.9},
                                      "simulations_per_s": None, "noise_floor": floor[0],
                                      "decision_tolerance": floor[1], "workers": 2, "efficiency": 0.5 + t / 100}))
    events.append(("finished", {}))
    stream = "".join(f"id: {i}\nevent: {e}\ndata: {json.dumps(d)}\n\n" for i, (e, d) in enumerate(events, 1))
    answers = {f"/jobs/{job}/view": ("text/html", VIEW), f"/jobs/{job}/events": ("text/event-stream", stream),
               f"/jobs/{job}": ("application/json", json.dumps({"id": job, "name": "toy", "models": ["linear", "cubic"],
                                                                "status": "running"})),
               f"/jobs/{job}/result": ("application/json", json.dumps({"warnings": []})),
               "/health": ("application/json", json.dumps({"workers": 2}))}

    def serve(route):
        fulfil_from(answers, route, route.request.url[len(origin):])

    page = browser.new_page(viewport={"width": 1200, "height": 900})
    page.route(f"{origin}/**", serve)
    page.goto(f"{origin}/jobs/{job}/view")
    wait_until(lambda: page.inner_text("#status") == "finished" and page.inner_text("#population") == "5", 30,
               "the five populations on the page")
    assert page.inner_text("#answer-at") == "population 3, \u03b5 3.333 % (decision tolerance 3.200 %, noise floor 2.800 %)"
    assert page.inner_text("#leader") == "linear (0.90)"
    assert page.inner_text("#efficiency") == "0.55"  # the last population's (issue O.5)
    assert read_all(page, "#eps text.mark-label", "t => t.textContent") == ["decision 3.200 %", "noise floor 2.800 %"]
    assert read_all(page, "#probs text.mark-label", "t => t.textContent") == ["answer (population 3)"]

    def box(selector: str) -> list[dict]:
        return read_all(page, selector, "e => { const b = e.getBoundingClientRect(); "
                                        "return {x: b.x, y: b.y, w: b.width, h: b.height, text: e.textContent}; }")

    # drawn where they belong: the marks across the tolerance curve (10 down to 2, top to bottom),
    # the decision above the floor; the answer's line at population 3's tick
    decision, floor = box("#eps line.mark")
    curve = box("#eps path")[0]
    assert decision["w"] > 100 and floor["w"] > 100
    assert curve["y"] < decision["y"] < floor["y"] < curve["y"] + curve["h"]
    (answer,) = box("#probs line.mark")
    tick = next(b for b in box("#probs text.lbl") if b["text"] == "3")
    assert answer["h"] > 100 and abs(answer["x"] - (tick["x"] + tick["w"] / 2)) < 2
    assert read_all(page, "#eps line.mark", "e => getComputedStyle(e).stroke") == ["rgb(0, 0, 0)"] * 2
    # the labels are filled text, not outlined in the grid's light grey (the chart's <div class="grid">
    # passed its stroke down to every <text>)
    strokes = read_all(page, "svg text", "t => getComputedStyle(t).stroke")
    assert strokes and set(strokes) == {"none"}, set(strokes)


def test_a_provisional_answer_says_so_on_the_page(browser):
    """Issue W: once a job has ended, the page shows the summary's answer: the model read by
    the likelihood over every population, and PROVISIONAL with the rule that stopped the run
    above its decision tolerance (here: max_populations at eps 2.0, decision 3.2 never
    reached), with the warning below. Served as above, with a result that says so."""
    from service.http.page import VIEW

    origin, job = "http://abcns.test", "0123456789abcdef"
    events = [("population", {"population": t, "epsilon": 10.0 / t, "epsilon_next": 10.0 / (t + 1),
                              "acceptance_rate": 0.5, "simulations": 1000 * t, "elapsed_s": float(t),
                              "model_probabilities": {"linear": 0.6, "cubic": 0.4}, "simulations_per_s": None,
                              "noise_floor": 1.0, "decision_tolerance": 1.2, "workers": 1, "efficiency": None})
              for t in (1, 2, 3)] + [("finished", {})]
    stream = "".join(f"id: {i}\nevent: {e}\ndata: {json.dumps(d)}\n\n" for i, (e, d) in enumerate(events, 1))
    warning = "provisional: the run stopped (max_populations) at eps 3.333, above the decision tolerance 1.2"
    result = {"warnings": [warning], "model_probabilities": {"linear": 0.25, "cubic": 0.75},
              "decision": {"population": 3, "epsilon": 10.0 / 3, "rule": "max_populations", "provisional": True,
                           "reading": "likelihood"}}
    answers = {f"/jobs/{job}/view": ("text/html", VIEW), f"/jobs/{job}/events": ("text/event-stream", stream),
               f"/jobs/{job}": ("application/json", json.dumps({"id": job, "name": "toy", "models": ["linear", "cubic"],
                                                                "status": "running"})),
               f"/jobs/{job}/result": ("application/json", json.dumps(result)),
               "/health": ("application/json", json.dumps({"workers": 1}))}
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    page.route(f"{origin}/**", lambda route: fulfil_from(answers, route, route.request.url[len(origin):]))
    page.goto(f"{origin}/jobs/{job}/view")
    wait_until(lambda: "warning: provisional" in page.inner_text("#warnings"), 30, "the warning on the page")
    assert page.inner_text("#leader") == "cubic (0.75) provisional"
    assert page.inner_text("#answer-at") == ("PROVISIONAL (stopped: max_populations, above the decision tolerance): "
                                             "populations 1-3 weighted by the likelihood, \u03b5 3.333 %")


def test_the_legend_stays_while_populations_come(browser):
    """The live page makes its legend again only when the models change, not on every event:
    the legend's elements that a reader holds (a person's selection, a test reading their
    colours) stay in the page while populations come. Served by Playwright's routing: the
    first event stream ends after two populations, so the page reconnects (Last-Event-ID);
    that request is held until the legend's elements are taken, then answered with two more
    populations and the end."""
    from service.http.page import CSP, VIEW

    origin, job, models = "http://abcns.test", "0123456789abcdef", ["linear", "cubic"]

    def population(t: int) -> dict:
        return {"population": t, "epsilon": 10.0 / t, "epsilon_next": 10.0 / (t + 1), "acceptance_rate": 0.5,
                "simulations": 1000 * t, "elapsed_s": float(t), "model_probabilities": {"linear": 0.6, "cubic": 0.4},
                "simulations_per_s": None, "noise_floor": None, "decision_tolerance": None, "workers": 2,
                "efficiency": 0.5}

    def stream(first_id: int, events: list) -> str:
        return "".join(f"id: {i}\nevent: {e}\ndata: {json.dumps(d)}\n\n" for i, (e, d) in enumerate(events, first_id))

    first = stream(1, [("queued", {"id": job, "name": "toy", "models": models, "distance": "nmse"}),
                       ("population", population(1)), ("population", population(2))])
    rest = stream(4, [("population", population(3)), ("population", population(4)), ("finished", {})])
    answers = {f"/jobs/{job}/view": ("text/html", VIEW),
               f"/jobs/{job}": ("application/json", json.dumps({"id": job, "name": "toy", "models": models,
                                                                "status": "running"})),
               f"/jobs/{job}/result": ("application/json", json.dumps({"warnings": []})),
               "/health": ("application/json", json.dumps({"workers": 2}))}
    streams: list = []  # the requests for the events, in order

    def serve(route):
        path = route.request.url[len(origin):]
        if path == f"/jobs/{job}/events":
            streams.append(route)
            if len(streams) == 1:
                route.fulfill(status=200, content_type="text/event-stream", body=first, headers={"Content-Security-Policy": CSP})
        else:
            fulfil_from(answers, route, path)

    page = browser.new_page(viewport={"width": 1200, "height": 900})
    page.route(f"{origin}/**", serve)
    page.goto(f"{origin}/jobs/{job}/view")
    wait_until(lambda: page.inner_text("#population") == "2", 30, "the first two populations on the page")
    legend = page.evaluate_handle("() => Array.from(document.querySelectorAll('#legend .model'))")
    # (the predicate calls the page, so Playwright answers its routes meanwhile)
    wait_until(lambda: page.inner_text("#population") and len(streams) == 2, 30, "the page to ask for the events again")
    assert streams[1].request.headers.get("last-event-id") == "3"
    streams[1].fulfill(status=200, content_type="text/event-stream", body=rest, headers={"Content-Security-Policy": CSP})
    wait_until(lambda: page.inner_text("#status") == "finished" and page.inner_text("#population") == "4", 30,
               "the last populations on the page")
    from service.report.colours import model_colour

    assert legend.evaluate("ss => ss.map(s => s.isConnected)") == [True, True]  # the same elements, still shown
    assert legend.evaluate("ss => ss.map(s => getComputedStyle(s).color)") == [rgb(model_colour(i)) for i in range(2)]
    assert read_all(page, "#legend .model", "s => s.textContent.trim()") == [f"\u25a0 {m}" for m in models]


XSS = '<img src=x onerror="document.title=\'pwned:\'+sessionStorage.getItem(\'abcns-token\')">'


def test_markup_in_names_is_shown_as_text_and_never_runs(browser, service):
    """N.1: a job and a model named with a script-carrying <img> are listed and viewed in
    Chromium: the names appear as text, no <img> element exists, nothing ran (the title is
    untouched, the token not read), and the pages carry the Content-Security-Policy."""
    spec = duffing_spec(max_populations=2, particles=200)
    spec["name"] = XSS
    spec["models"][0]["name"] = XSS
    r = httpx.post(f"{service.url}/jobs", json=spec, headers=AUTH, timeout=60)
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    for path in ("/", f"/jobs/{job_id}/view"):
        response = httpx.get(f"{service.url}{path}", timeout=30)
        assert "script-src" in response.headers.get("content-security-policy", "")
        page = browser.new_page()
        ran: list[str] = []
        page.on("dialog", lambda d: (ran.append(d.message), d.dismiss()))
        page.goto(f"{service.url}{path}#token={TOKEN}")
        where = "#jobs" if path == "/" else "#name"
        wait_until(lambda: XSS in page.inner_text(where), 60, f"the name as text on {path}")
        if path != "/":
            wait_until(lambda: page.inner_text("#status") == "finished", 120, "the job to finish on the page")
        page.wait_for_timeout(500)
        assert page.locator("img").count() == 0
        assert "pwned" not in page.title() and not ran


def test_api_docs_render_offline(browser, service):
    """I.4: /docs draws Swagger UI from the service's own files; every request that would
    leave the service is aborted, and the page still lists the API's routes."""
    page = browser.new_page()
    outside: list[str] = []

    def only_local(route):
        if route.request.url.startswith(service.url):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", only_local)
    page.goto(f"{service.url}/docs")
    wait_until(lambda: "/jobs/{job_id}/events" in page.inner_text("body"), 60, "the routes on /docs")
    assert outside == []


def test_labels_apart_distinct_ticks_and_the_workers_as_a_chart(browser):
    """Issue AA, point 4: the noise floor's and the decision's labels do not overlap when the
    two are close (here 2.80 and 2.90 %: 2 px apart on the chart); a narrow marginal
    (1.4903-1.4919) gets tick labels that differ; the workers per population are a chart.
    Served by Playwright's routing, as above."""
    from service.http.page import VIEW

    origin, job = "http://abcns.test", "0123456789abcdef"
    events = [("population", {"population": t, "epsilon": 10.0 / t, "epsilon_next": 10.0 / (t + 1),
                              "acceptance_rate": 0.5, "simulations": 1000 * t, "elapsed_s": float(t),
                              "model_probabilities": {"linear": 1.0}, "simulations_per_s": None,
                              "noise_floor": 2.8, "decision_tolerance": 2.9, "workers": [1, 2, 2, 3][t - 1],
                              "efficiency": 0.5}) for t in (1, 2, 3, 4)] + [("finished", {})]
    stream = "".join(f"id: {i}\nevent: {e}\ndata: {json.dumps(d)}\n\n" for i, (e, d) in enumerate(events, 1))
    m = [1.4903 + 0.0016 * i / 39 for i in range(40)]
    pop = {"offset": 0, "n_particles": 40, "distances": [1.0] * 40, "models": [0] * 40,
           "theta": [[v, 10.0 + i] for i, v in enumerate(m)], "model_names": ["linear"],
           "parameter_names": [["m", "k"]], "model_probabilities": [1.0]}
    answers = {f"/jobs/{job}/view": ("text/html", VIEW), f"/jobs/{job}/events": ("text/event-stream", stream),
               f"/jobs/{job}": ("application/json", json.dumps({"id": job, "name": "toy", "models": ["linear"],
                                                                "status": "running"})),
               **{f"/jobs/{job}/populations/{t}?limit=10000": ("application/json", json.dumps(pop)) for t in (1, 2, 3, 4)},
               f"/jobs/{job}/result": ("application/json", json.dumps({"warnings": []})),
               "/health": ("application/json", json.dumps({"workers": 3}))}
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    page.route(f"{origin}/**", lambda route: fulfil_from(answers, route, route.request.url[len(origin):]))
    page.goto(f"{origin}/jobs/{job}/view")
    wait_until(lambda: page.inner_text("#status") == "finished" and "population 4" in page.inner_text("#hists"), 30,
               "the four populations and the marginals")
    boxes = read_all(page, "#eps text.mark-label", "e => { const b = e.getBoundingClientRect(); "
                                                   "return [b.top, b.bottom, e.textContent]; }")
    (_, bottom_a, text_a), (top_b, _, text_b) = boxes
    assert text_a.startswith("decision") and text_b.startswith("noise floor")
    assert bottom_a <= top_b, boxes  # the decision's label wholly above the floor's
    ticks = page.evaluate("""() => Array.from(document.querySelectorAll("#hists .hist svg"),
        s => Array.from(s.querySelectorAll("text.lbl"), t => t.textContent))""")
    assert len(ticks) == 2 and all(len(set(t)) == 3 for t in ticks), ticks
    assert ticks[0] == ["1.49", "1.491", "1.492"], ticks  # 4 digits (1.490, trailing zero dropped), not 1.49 1.49 1.49
    assert page.locator("#workers-chart path").count() == 1
    assert read_all(page, "#workers-chart text.axis-title", "t => t.textContent") == ["population", "workers"]
    assert {"0", "1", "2", "3"} <= set(read_all(page, "#workers-chart text.lbl", "t => t.textContent"))


def test_a_study_page_fills_its_confusion_matrix_in(browser):
    """Issue V: a study's page shows its progress and its confusion matrix filling in. Served
    as the service serves it (its HTML and Content-Security-Policy) by Playwright's routing,
    GET /studies/{id} first answers 2 of 4 data sets finished (one confusion), then all 4; the
    page's cells, counts, ECE and coverage are read as a person sees them."""
    from service.http.page import STUDY, STUDY_CSP

    origin, study = "http://abcns.test", "fedcba9876543210"

    def answer(finished: int, counts: list, ece: float | None) -> str:
        rates = [[n / sum(row) if sum(row) else None for n in row] for row in counts]
        return json.dumps({"id": study, "datasets": 4, "finished": finished, "done": finished == 4,
                           "counts": {"finished": finished, "queued": 4 - finished} if finished < 4 else {"finished": 4},
                           "confusion_matrix": {"models": ["linear", "cubic"], "counts": counts, "rates": rates},
                           "calibration": {"ece": ece, "ece_interval": None if ece is None else [0.01, 0.2]},
                           "coverage": {"all": {"n": 2 * finished, "cover50": 0.5, "cover95": 1.0}}})

    answers = [answer(2, [[1, 0], [1, 0]], None), answer(4, [[2, 0], [1, 1]], 0.125)]
    asked = []

    def serve(route):
        path = route.request.url[len(origin):]
        if path == f"/studies/{study}/view":
            route.fulfill(status=200, content_type="text/html", body=STUDY, headers={"Content-Security-Policy": STUDY_CSP})
        elif path == f"/studies/{study}":
            asked.append(path)
            route.fulfill(status=200, content_type="application/json", body=answers[min(len(asked), 2) - 1])
        else:
            route.fulfill(status=404, body="")

    page = browser.new_page(viewport={"width": 1000, "height": 700})
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.route(f"{origin}/**", serve)
    page.goto(f"{origin}/studies/{study}/view")
    wait_until(lambda: page.inner_text("#progress") == "2 of 4 finished", 30, "the first answer on the page")
    rows = lambda: read_all(page, "#confusion tr", "r => Array.from(r.children).map(c => c.textContent)")
    assert rows() == [["linear", "1 (1.00)", "0 (0.00)"], ["cubic", "1 (1.00)", "0 (0.00)"]]
    assert page.inner_text("#ece") == "-"
    wait_until(lambda: page.inner_text("#progress") == "4 of 4 finished", 30, "the study's end on the page")
    assert rows() == [["linear", "2 (1.00)", "0 (0.00)"], ["cubic", "1 (0.50)", "1 (0.50)"]]
    assert read_all(page, "#confusion-head th", "t => t.textContent") == ["true \\ chosen", "linear", "cubic"]
    assert page.inner_text("#ece") == "0.125 [0.010, 0.200]"
    assert page.inner_text("#cover") == "50 %: 0.500, 95 %: 1.000 of 8 pairs"
    assert page.inner_text("#counts") == "finished 4" and page.inner_text("#error") == ""
    assert len(asked) == 2, "the page stops asking once the study is done"
    assert not [e for e in errors if "Content Security Policy" in e], errors
