"""The viewer as a user feels it: time to the first image after opening the page, the sizes of the
images as they refine, and frames per second while dragging, in headless Chromium.

    python benchmarks/bench_viewer.py --run RUN [--window-size 1000,700] [--drag-seconds 5]

RUN is a trained run's folder (or its config.yml). The benchmark starts ``ns-viewer --load-config
RUN/config.yml`` on a free port as a user would (a subprocess, in the folder the run's relative paths
start from, with this checkout first on PYTHONPATH), waits until the page answers, then opens it in
headless Chromium (selenium; --headless=new --disable-gpu --enable-unsafe-swiftshader).

Method. A script installed in the page before it loads (CDP Page.addScriptToEvaluateOnNewDocument)
watches the messages viser's websocket worker hands to the page, and records every
``BackgroundImageMessage`` (the rendered image the server sends; viser draws it behind the scene) with
its arrival time (wall clock, the same clock as this script's), its size in pixels (decoded in the
page) and whether it is blank (pixel standard deviation < 2 of 255). Nothing in the viewer or viser
is patched; the figures are what reaches the browser.

* first image: the page is opened once ns-viewer answers and has gone idle (its start-up is over, as
  for a user who opens the address it printed); seconds from ``driver.get()`` to the arrival of the first non-blank rendered image;
  then every image until the first at the viewer's full size ("Max res", default 512) or a time-out.
* dragging: a left-button drag over the 3D view with selenium ActionChains (press, small moves every
  ``--move-interval`` seconds for ``--drag-seconds``, release); frames per second = rendered images
  that arrive between press and release / drag duration (coarse frames count), with their sizes.
* the panel: whether "Pause Training"/"Resume Training" are shown and the "Step:" line.

Chromium shares the CPU with the viewer (the page draws with SwiftShader), as on a user's machine
without a GPU. Figures print as a table and a one-line JSON summary.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Dict, List, Tuple

REPO = Path(__file__).resolve().parents[1]

#: Installed in the page before it loads: records each rendered image viser's websocket worker hands
#: to the page (the worker posts {type: "message_batch", messages}); window.__frames holds them.
PAGE_HOOK = r"""
(() => {
  window.__frames = [];
  window.__cameras = [];  // camera messages the page sends the server
  window.__events = {};  // first time (wall clock, ms) of: connected, scene (first message batch), camera_sent
  const first = (name) => { if (!(name in window.__events)) window.__events[name] = Date.now(); };
  window.__longtasks = [];  // the page's main thread busy > 50 ms at a time: [start, end], wall clock ms
  new PerformanceObserver((list) => {
    for (const task of list.getEntries()) {
      const start = performance.timeOrigin + task.startTime;
      window.__longtasks.push([start, start + task.duration]);
    }
  }).observe({type: "longtask", buffered: true});
  const OriginalWorker = window.Worker;
  function record(message) {
    const entry = {t: Date.now(), bytes: message.rgb_bytes.byteLength, w: 0, h: 0, std: -1};
    window.__frames.push(entry);
    createImageBitmap(new Blob([message.rgb_bytes], {type: message.media_type})).then((bitmap) => {
      entry.w = bitmap.width; entry.h = bitmap.height;
      const canvas = new OffscreenCanvas(bitmap.width, bitmap.height);
      const context = canvas.getContext("2d");
      context.drawImage(bitmap, 0, 0);
      const data = context.getImageData(0, 0, bitmap.width, bitmap.height).data;
      let sum = 0, sum2 = 0, n = 0;
      for (let i = 0; i < data.length; i += 4) {
        for (let c = 0; c < 3; c++) { const v = data[i + c]; sum += v; sum2 += v * v; n++; }
      }
      const mean = sum / n;
      entry.std = Math.sqrt(Math.max(0, sum2 / n - mean * mean));
    });
  }
  window.Worker = class extends OriginalWorker {
    constructor(...args) {
      super(...args);
      this.addEventListener("message", (event) => {
        const data = event.data;
        if (data && data.type === "connected") first("connected");
        if (data && data.type === "message_batch") {
          first("scene");
          for (const message of data.messages) {
            if (message.type === "BackgroundImageMessage") record(message);
          }
        }
      });
    }
    postMessage(data, ...rest) {
      if (data && data.type === "send" && data.message && data.message.type === "ViewerCameraMessage") {
        first("camera_sent");
        const m = data.message;
        window.__cameras.push({t: Date.now(), aspect: m.aspect, fov: m.fov, position: m.position, wxyz: m.wxyz});
      }
      return super.postMessage(data, ...rest);
    }
  };
})();
"""

#: The 3D view: the page's largest canvas.
LARGEST_CANVAS = "Array.from(document.querySelectorAll('canvas')).sort((a, b) => b.clientWidth * b.clientHeight - a.clientWidth * a.clientHeight)[0]"

#: Returns the panel's state: the train buttons shown and the stats markdown's lines.
PANEL_STATE = r"""
const shown = (label) => Array.from(document.querySelectorAll("button")).some(
  (b) => b.textContent.trim() === label && b.offsetParent !== null);
const step = Array.from(document.querySelectorAll("p, div")).map((e) => e.textContent)
  .find((t) => /^\s*Step: \d+/.test(t) && t.length < 80) || "";
return {pause: shown("Pause Training"), resume: shown("Resume Training"), stats: step.trim()};
"""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def run_folder_and_cwd(run: Path) -> Tuple[Path, Path]:
    """(config.yml, the folder ns-viewer must start in for the run's relative paths to resolve)."""
    import yaml

    config_path = run if run.name == "config.yml" else run / "config.yml"
    if not config_path.is_file():
        raise SystemExit(f"no config.yml at {config_path}")
    class Loader(yaml.SafeLoader):  # reads nerfstudio's python/object tags as plain data (imports nothing)
        pass

    def plain(loader, suffix, node):
        if "PosixPath" in suffix or "WindowsPath" in suffix:
            return str(Path(*loader.construct_sequence(node)))
        if isinstance(node, yaml.MappingNode):
            return loader.construct_mapping(node, deep=True)
        return loader.construct_sequence(node, deep=True) if isinstance(node, yaml.SequenceNode) else None

    Loader.add_multi_constructor("tag:yaml.org,2002:python/", plain)
    config = yaml.load(config_path.read_text(), Loader=Loader)
    output_dir = Path(config["output_dir"])
    cwd = Path.cwd()
    if not output_dir.is_absolute():  # RUN = cwd / output_dir / experiment / method / timestamp
        cwd = config_path.resolve().parent.parents[len(output_dir.parts) + 2]
    data = Path(config["data"]) if config.get("data") is not None else None
    if data is not None and not (data if data.is_absolute() else cwd / data).exists():
        raise SystemExit(f"the run's data {data} is not there (looked in {cwd})")
    return config_path.resolve(), cwd


def start_viewer(config: Path, cwd: Path, port: int, log_path: Path) -> subprocess.Popen:
    command = shutil.which("ns-viewer")
    argv = [command] if command else [sys.executable, "-m", "nerfstudio.scripts.viewer.run_viewer"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    log = open(log_path, "w")
    return subprocess.Popen([*argv, "--load-config", str(config), "--viewer.websocket-port", str(port)],
                            cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)


def wait_for_page(viewer: subprocess.Popen, port: int, timeout: float, log_path: Path) -> float:
    start = time.time()
    while time.time() - start < timeout:
        if viewer.poll() is not None:
            raise SystemExit(f"ns-viewer ended (exit {viewer.returncode}):\n{log_path.read_text()[-3000:]}")
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).close()
            return time.time() - start
        except OSError:
            time.sleep(0.2)
    raise SystemExit(f"ns-viewer did not answer within {timeout:.0f} s:\n{log_path.read_text()[-3000:]}")


def wait_idle(viewer: subprocess.Popen, timeout: float, window: float = 1.0, busy: float = 0.1) -> float:
    """Wait until ns-viewer has finished starting (its CPU use over ``window`` s below ``busy`` of a core);
    the seconds waited. The page answers as soon as viser's server runs, before the viewer has drawn its
    scene and is ready to render."""
    import psutil

    process, start = psutil.Process(viewer.pid), time.time()
    while time.time() - start < timeout:
        before = sum(process.cpu_times()[:2])
        time.sleep(window)
        if sum(process.cpu_times()[:2]) - before < busy * window:
            break
    return time.time() - start


def browser(window_size: str):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    chromedriver = shutil.which("chromedriver")
    if chromium is None or chromedriver is None:
        raise SystemExit("chromium and chromedriver are needed (tools/setup-tests.sh installs them)")
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", f"--window-size={window_size}", "--enable-unsafe-swiftshader"):
        options.add_argument(argument)
    driver = webdriver.Chrome(service=Service(chromedriver), options=options)
    driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": PAGE_HOOK})
    return driver


def frames(driver) -> List[Dict]:
    return driver.execute_script("return window.__frames || [];")


def wait_frames(driver, until, timeout: float, poll: float = 0.05) -> List[Dict]:
    deadline = time.time() + timeout
    while True:
        current = frames(driver)
        if until(current) or time.time() > deadline:
            return current
        time.sleep(poll)


def drag(driver, seconds: float, interval: float, step_px: int) -> Tuple[float, float]:
    """A left-button drag over the middle of the 3D view; (press time, release time), wall clock."""
    from selenium.webdriver.common.action_chains import ActionChains
    canvas = driver.execute_script(f"return {LARGEST_CANVAS};")
    moves = max(1, int(seconds / interval))
    chain = ActionChains(driver, duration=0)
    chain.move_to_element_with_offset(canvas, -canvas.size["width"] // 4, 0).click_and_hold()
    for i in range(moves):
        # right for the first half, back for the second: the view turns and comes back
        chain.move_by_offset(step_px if i < moves // 2 else -step_px, 0).pause(interval)
    chain.release()
    start = time.time()
    chain.perform()
    return start, time.time()


def busy(longtasks: List[List[float]], start_ms: float, end_ms: float) -> float:
    """Seconds of the page's long tasks that fall between two wall-clock times (ms)."""
    return round(sum(max(0.0, min(end, end_ms) - max(begin, start_ms)) for begin, end in longtasks) / 1000, 2)


def size(frame: Dict) -> str:
    return f"{frame['w']}x{frame['h']}"


def measure(args: argparse.Namespace) -> Dict:
    config, cwd = run_folder_and_cwd(Path(args.run))
    port = free_port()
    log_path = Path(args.log) if args.log else Path(f"/tmp/bench-viewer-{port}.log")
    started = time.time()
    viewer = start_viewer(config, cwd, port, log_path)
    driver = None
    try:
        startup_s = wait_for_page(viewer, port, args.startup_timeout, log_path)
        startup_s += wait_idle(viewer, args.startup_timeout)
        driver = browser(args.window_size)
        t0 = time.time()
        driver.get(f"http://127.0.0.1:{port}/")
        loaded_s = time.time() - t0
        full_height = args.max_res

        def settled(current: List[Dict]) -> bool:
            return any(f["h"] >= full_height * 0.9 or f["w"] >= full_height * 0.9 for f in current)

        opening = wait_frames(driver, settled, args.settle_timeout)
        time.sleep(0.5)  # let the last image decode
        opening = frames(driver)
        events = driver.execute_script("return window.__events || {};")
        longtasks = driver.execute_script("return window.__longtasks || [];")
        canvas = driver.execute_script(f"const c = {LARGEST_CANVAS}; return [c.clientWidth, c.clientHeight];")
        panel = driver.execute_script(PANEL_STATE)
        non_blank = [f for f in opening if f["std"] >= 2.0]
        first = non_blank[0] if non_blank else None

        time.sleep(args.rest)
        before = len(frames(driver))
        press, release = drag(driver, args.drag_seconds, args.move_interval, args.step_px)
        time.sleep(0.3)
        during = [f for f in frames(driver)[before:] if press <= f["t"] / 1000 <= release]
        after_drag = wait_frames(driver, lambda c: settled(c[before + len(during):]), args.settle_timeout)
        after = [f for f in after_drag[before:] if f["t"] / 1000 > release]
        return {
            "run": str(config.parent), "window": args.window_size, "canvas": canvas, "viewer_startup_s": round(startup_s, 2),
            "page_load_s": round(loaded_s, 2),
            "first_image_s": round(first["t"] / 1000 - t0, 2) if first else None,
            "first_image": size(first) if first else None,
            "page_events": {name: round(t / 1000 - t0, 2) for name, t in sorted(events.items(), key=lambda item: item[1])},
            "page_busy_before_first_image_s": busy(longtasks, 0.0, first["t"]) if first else None,
            "page_busy_camera_to_first_image_s": busy(longtasks, events.get("camera_sent", first["t"]), first["t"]) if first else None,
            "opening": [(round(f["t"] / 1000 - t0, 2), size(f)) for f in opening],
            "drag_s": round(release - press, 2), "drag_frames": len(during),
            "drag_fps": round(len(during) / max(1e-6, release - press), 2),
            "drag_sizes": sorted({size(f) for f in during}),
            "after_release": [(round(f["t"] / 1000 - release, 2), size(f)) for f in after],
            "panel": panel, "total_s": round(time.time() - started, 1),
        }
    finally:
        if driver is not None:
            driver.quit()
        viewer.terminate()
        try:
            viewer.wait(timeout=30)
        except subprocess.TimeoutExpired:
            viewer.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", required=True, help="a trained run's folder (or its config.yml)")
    parser.add_argument("--window-size", default="1000,700", help="Chromium's window, W,H in pixels")
    parser.add_argument("--max-res", type=int, default=512, help="the viewer's Max res (its default): an image this large is the full render")
    parser.add_argument("--drag-seconds", type=float, default=5.0, help="length of the drag, seconds")
    parser.add_argument("--move-interval", type=float, default=0.05, help="seconds between the drag's mouse moves")
    parser.add_argument("--step-px", type=int, default=4, help="pixels per mouse move")
    parser.add_argument("--rest", type=float, default=1.0, help="seconds between the full image and the drag")
    parser.add_argument("--startup-timeout", type=float, default=300.0, help="seconds to wait for ns-viewer's page")
    parser.add_argument("--settle-timeout", type=float, default=120.0, help="seconds to wait for a full-size image")
    parser.add_argument("--log", help="ns-viewer's output goes here (default /tmp/bench-viewer-PORT.log)")
    args = parser.parse_args()
    result = measure(args)
    print(f"run: {result['run']}  window {result['window']}, 3D view {result['canvas'][0]}x{result['canvas'][1]} px, Max res {args.max_res}")
    print(f"ns-viewer answered and went idle after {result['viewer_startup_s']} s; page loaded (driver.get) in {result['page_load_s']} s")
    print("page (s after driver.get): " + ", ".join(f"{name} {t}" for name, t in result["page_events"].items()))
    print(f"first non-blank image: {result['first_image']} at {result['first_image_s']} s after driver.get(); "
          f"the page's main thread was busy (long tasks) {result['page_busy_before_first_image_s']} s before it, "
          f"{result['page_busy_camera_to_first_image_s']} s of that after it sent its camera")
    print("images after opening (s after driver.get, WxH): " + ", ".join(f"{t} {s}" for t, s in result["opening"]))
    print(f"drag: {result['drag_frames']} images in {result['drag_s']} s = {result['drag_fps']} fps, sizes {result['drag_sizes']}")
    print("after release (s after release, WxH): " + ", ".join(f"{t} {s}" for t, s in result["after_release"]))
    print(f"panel: Pause Training shown: {result['panel']['pause']}, Resume Training shown: {result['panel']['resume']}, "
          f"stats: {result['panel']['stats']!r}")
    print("summary: " + json.dumps({k: result[k] for k in ("first_image_s", "first_image", "page_busy_before_first_image_s", "drag_fps", "drag_frames", "drag_sizes", "panel")}))


if __name__ == "__main__":
    main()
