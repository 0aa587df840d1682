"""Retake the MLflow UI pictures in docs/img: a first visit to the link endoflow prints for a project's training
experiment (its runs table, with the run names and the headline metrics as columns) and its registered model.

Usage, from the root of a project that has run (for example the smoke ablations of README's DVC section):
``python docs/mlflow_screenshot.py [--project .] [--out docs/img]``. It starts ``mlflow ui`` on the project's
store (bound to 127.0.0.1, a free port), drives Debian's headless Chromium (``apt-get install chromium``) over
the DevTools protocol on a pipe (no other package needed) with a fresh profile, as a first visit, opens
:func:`endoflow.tracking.runs_table_path` and writes ``mlflow_runs.png`` and ``mlflow_model.png``; it fails if
the page is not the runs table with the headline columns.
"""

from __future__ import annotations

import argparse
import base64
import fcntl
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any, Callable

from endoflow import tracking
from endoflow.config import load_params
from endoflow.io import write_bytes

WINDOW = (1920, 960)
PAGE_TIMEOUT_S = 60.0
# the UI's own switch between its GenAI and model-training sidebars, as a link carries it
MODEL_TRAINING_VIEW = f"workflowType={tracking.MODEL_TRAINING_WORKFLOW}"
# MLflow's assistant panel opens itself on a first visit, over a third of the page
CLOSE_ASSISTANT = ("document.querySelector('[data-component-id=\"mlflow.assistant.chat_panel.close\"]')"
                   "?.click()")


class DevTools:
    """The Chrome DevTools protocol over ``--remote-debugging-pipe``: JSON messages ending in NUL, commands
    on the browser's fd 3, replies and events on its fd 4."""

    def __init__(self, chromium: str, user_data: str) -> None:
        to_browser, self._commands = os.pipe()
        self._replies, from_browser = os.pipe()

        def browser_fds() -> None:
            # via fds above 4 first: a pipe end may itself be fd 3 or 4, and dup2 onto itself keeps close-on-exec
            high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_browser, from_browser)]
            for fd, target in zip(high, (3, 4)):
                os.dup2(fd, target)

        self.process = subprocess.Popen(
            [chromium, "--headless=new", "--remote-debugging-pipe", "--no-sandbox", "--disable-gpu",
             "--no-first-run", "--hide-scrollbars", f"--user-data-dir={user_data}",
             f"--window-size={WINDOW[0]},{WINDOW[1]}", "about:blank"],
            # the pipes must arrive as fds 3 and 4, which closing the parent's fds would undo
            preexec_fn=browser_fds, close_fds=False,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(to_browser)
        os.close(from_browser)
        self._buffer = b""
        self._next_id = 0
        self.session = ""

    def call(self, method: str, **params: Any) -> dict:
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params}
        if self.session:
            message["sessionId"] = self.session
        os.write(self._commands, json.dumps(message).encode() + b"\0")
        while True:
            reply = self._read()
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def _read(self) -> dict:
        while b"\0" not in self._buffer:
            block = os.read(self._replies, 1 << 20)
            if not block:
                raise RuntimeError("Chromium closed the DevTools pipe")
            self._buffer += block
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def open_page(self) -> None:
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        self.call("Emulation.setDeviceMetricsOverride", width=WINDOW[0], height=WINDOW[1], deviceScaleFactor=1,
                  mobile=False)

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (a promise's, once it settles)."""
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                         awaitPromise=True)["result"].get("value")

    def show(self, url: str, ready: Callable[[], bool]) -> None:
        self.call("Page.navigate", url=url)
        deadline = time.monotonic() + PAGE_TIMEOUT_S
        while not ready():
            if time.monotonic() > deadline:
                raise TimeoutError(f"{url}: the page did not show what was expected in {PAGE_TIMEOUT_S:.0f} s")
            time.sleep(0.5)
        time.sleep(2.0)  # fonts, icons and the table's column sizing settle after the data arrives

    def screenshot(self, path: Path) -> None:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        write_bytes(path, base64.b64decode(data))
        print(f"wrote {path}")

    def close(self) -> None:
        self.session = ""
        try:
            self.call("Browser.close")
        except RuntimeError:
            pass
        self.process.wait(timeout=30)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(store: str, artifacts: str, port: int) -> subprocess.Popen:
    server = subprocess.Popen(
        [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", store, "--default-artifact-root",
         artifacts, "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + PAGE_TIMEOUT_S
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2):
                return server
        except OSError:
            if server.poll() is not None or time.monotonic() > deadline:
                server.kill()
                raise RuntimeError(f"mlflow server on {store} did not start")
            time.sleep(0.5)


# the runs table's columns: the table draws only those in sight, so scroll across it and note each one's id
SHOWN_COLUMNS = """(async () => {
    const seen = new Set(), table = document.querySelector('.ag-body-horizontal-scroll-viewport');
    for (let left = 0; table && left <= table.scrollWidth; left += table.clientWidth / 2) {
        table.scrollLeft = left;
        await new Promise(settled => setTimeout(settled, 300));
        document.querySelectorAll('.ag-header-cell[col-id]').forEach(cell => seen.add(cell.getAttribute('col-id')));
    }
    if (table) { table.scrollLeft = 0; }
    await new Promise(settled => setTimeout(settled, 300));
    return Array.from(seen);
})()"""


def shown_metrics(browser: "DevTools") -> list[str]:
    """The metrics the runs table shows as columns."""
    return [column[len("metrics.`"):-1] for column in browser.evaluate(SHOWN_COLUMNS)
            if column.startswith("metrics.`")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--project", type=Path, default=Path("."), help="project root (default: .)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "img", help="folder for the PNGs")
    args = parser.parse_args()
    chromium = shutil.which("chromium")
    if chromium is None:
        sys.exit("Chromium is not on PATH; on Debian: apt-get install chromium")
    project = args.project.resolve()
    params = load_params(project / "params.yaml")
    uri = tracking.tracking_uri(params, project)
    if not uri.startswith("sqlite:///"):
        sys.exit(f"tracking.uri is {uri}: open that server's UI instead")
    client = tracking.client(uri)
    experiment = client.get_experiment_by_name(params.tracking.experiment)
    if experiment is None:
        sys.exit(f"{uri} has no experiment {params.tracking.experiment!r}: run the pipeline first")
    runs = client.search_runs([experiment.experiment_id])
    if not runs:
        sys.exit(f"experiment {params.tracking.experiment!r} has no runs: run the pipeline first")
    view = json.loads(experiment.tags.get(tracking.RUNS_VIEW_TAG, "{}")).get("selectedColumns", [])
    headline = [column[len("metrics.`"):-1] for column in view if column.startswith("metrics.")]
    if not headline:
        sys.exit(f"experiment {params.tracking.experiment!r} has no headline columns: evaluate a model first")
    models = client.search_registered_models()

    port = free_port()
    base = f"http://127.0.0.1:{port}/"
    server = start_server(uri, tracking.artifact_location(params, project) or str(project / "mlartifacts"), port)
    try:
        with tempfile.TemporaryDirectory(prefix="endoflow-chromium-") as user_data:
            browser = DevTools(chromium, user_data)
            try:
                browser.open_page()
                names = [run.info.run_name for run in runs]
                browser.show(base + tracking.runs_table_path(experiment.experiment_id),
                             lambda: all(browser.evaluate(f"document.body.innerText.includes({json.dumps(n)})")
                                         for n in names))
                missing = sorted(set(headline) - set(shown_metrics(browser)))
                if missing:
                    sys.exit(f"the runs table a first visit opens lacks the headline columns {missing}")
                browser.evaluate(CLOSE_ASSISTANT)
                time.sleep(1.0)
                browser.screenshot(args.out / "mlflow_runs.png")
                if models:
                    name = models[0].name
                    newest = max(int(v.version) for v in client.search_model_versions(f"name = '{name}'"))
                    browser.show(f"{base}#/models/{name}?{MODEL_TRAINING_VIEW}",
                                 lambda: browser.evaluate(f"document.body.innerText.includes('Version {newest}')"))
                    browser.evaluate(CLOSE_ASSISTANT)
                    time.sleep(1.0)
                    browser.screenshot(args.out / "mlflow_model.png")
            finally:
                browser.close()
    finally:
        server.terminate()
        server.wait(timeout=30)


if __name__ == "__main__":
    main()
