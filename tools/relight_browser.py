#!/usr/bin/env python3
"""Drive `canopy relight VIEW.relight --serve` from a real browser (headless Chromium).

Opens the page, waits for the first image, moves the first lamp's strength slider (or
the first light's intensity) and waits for the image to change, saving a screenshot before
and after. Fails unless the page shows a new, brighter image after the move.

Needs Debian's chromium and chromium-driver and `pip install selenium`.

    python3 tools/relight_browser.py VIEW.relight --out DIR [--canopy target/release/canopy]
"""
import argparse
import pathlib
import subprocess
import sys
import time

from selenium import webdriver
from selenium.webdriver.common.by import By

# The mean red of the image element's pixels, read back through a canvas.
MEAN_JS = """
const img = document.getElementById('view');
if (!img.complete || img.naturalWidth == 0) return [null, 0, ''];
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const g = c.getContext('2d'); g.drawImage(img, 0, 0);
const d = g.getImageData(0, 0, c.width, c.height).data;
let s = 0; for (let i = 0; i < d.length; i += 4) s += d[i];
return [img.src, s / (d.length / 4), document.getElementById('status').textContent];
"""


def wait_for(driver, old_src, timeout=60):
    end = time.time() + timeout
    while time.time() < end:
        src, mean, status = driver.execute_script(MEAN_JS)
        if src and src != old_src and "frame" in status:
            return src, mean, status
        time.sleep(0.2)
    sys.exit("the page showed no new image in %d s" % timeout)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("view")
    ap.add_argument("--out", required=True)
    ap.add_argument("--canopy", default="target/release/canopy")
    a = ap.parse_args()
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    server = subprocess.Popen(
        [a.canopy, "relight", a.view, "--serve", "127.0.0.1:0"],
        stdout=subprocess.PIPE, text=True)
    try:
        line = server.stdout.readline()
        url = line.split()[1]
        opts = webdriver.ChromeOptions()
        for flag in ("--headless=new", "--no-sandbox", "--window-size=1100,700"):
            opts.add_argument(flag)
        opts.binary_location = "/usr/bin/chromium"
        service = webdriver.ChromeService(executable_path="/usr/bin/chromedriver")
        driver = webdriver.Chrome(options=opts, service=service)
        try:
            driver.get(url)
            src, before, status = wait_for(driver, None)
            print("before:", round(before, 1), status)
            driver.save_screenshot(str(out / "relight_before.png"))
            slider = driver.find_elements(By.CSS_SELECTOR, "input[type=range]")[0]
            driver.execute_script(
                "arguments[0].value = arguments[0].max;"
                "arguments[0].dispatchEvent(new Event('input'));", slider)
            _, after, status = wait_for(driver, src)
            print("after:", round(after, 1), status)
            driver.save_screenshot(str(out / "relight_after.png"))
            if not after > before * 1.2:
                sys.exit("moving the control did not brighten the image (%.1f -> %.1f)"
                         % (before, after))
        finally:
            driver.quit()
    finally:
        server.kill()


if __name__ == "__main__":
    main()
