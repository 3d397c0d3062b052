//! The relight page in a real browser: headless Chromium, driven through ChromeDriver's
//! WebDriver protocol (plain HTTP and JSON), loads the page `canopy relight --serve` serves,
//! shows the relit image, and after a click moves the lamp's strength slider shows a brighter
//! one with the frame time. Skipped, saying so, where Chromium or ChromeDriver is not
//! installed (Debian: `apt-get install chromium chromium-driver`; `.ci/run` installs them
//! when it runs as root with apt-get).

mod common;
use base64::Engine;
use common::*;
use serde_json::{json, Value};
use std::io::{BufRead, Read, Write};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// One WebDriver command: `method` on `path` with an optional JSON body; returns `value`.
/// HTTP/1.1 (ChromeDriver refuses 1.0), one connection per command.
fn webdriver(port: u16, method: &str, path: &str, body: Option<Value>) -> Value {
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut r = std::io::BufReader::new(s);
    let mut length = None;
    loop {
        let mut line = String::new();
        r.read_line(&mut line).unwrap();
        let line = line.trim_end();
        if line.is_empty() {
            break;
        }
        if let Some((k, v)) = line.split_once(':') {
            if k.eq_ignore_ascii_case("content-length") {
                length = v.trim().parse::<usize>().ok();
            }
        }
    }
    let mut out = Vec::new();
    match length {
        Some(n) => {
            out.resize(n, 0);
            r.read_exact(&mut out).unwrap();
        }
        None => {
            r.read_to_end(&mut out).unwrap();
        }
    }
    let reply: Value = serde_json::from_slice(&out).unwrap_or(Value::Null);
    assert!(
        reply["value"].get("error").is_none(),
        "{method} {path}: {}",
        reply["value"]
    );
    reply["value"].clone()
}

/// Polls `script` in the page until it returns true.
fn wait_for(port: u16, session: &str, script: &str, what: &str) {
    let start = Instant::now();
    let path = format!("/session/{session}/execute/sync");
    while webdriver(
        port,
        "POST",
        &path,
        Some(json!({"script": script, "args": []})),
    ) != Value::Bool(true)
    {
        assert!(start.elapsed() < Duration::from_secs(60), "{what}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Mean red of the relit image as the browser shows it (a screenshot of the element).
fn shown_red(port: u16, session: &str, element: &str) -> f64 {
    let shot = webdriver(
        port,
        "GET",
        &format!("/session/{session}/element/{element}/screenshot"),
        None,
    );
    let png = base64::engine::general_purpose::STANDARD
        .decode(shot.as_str().unwrap())
        .unwrap();
    let img = image::load_from_memory(&png).unwrap().to_rgb8();
    let n = img.pixels().len() as f64;
    img.pixels().map(|p| p[0] as f64).sum::<f64>() / n
}

#[test]
fn the_relight_page_shows_a_brighter_image_when_the_lamp_slider_moves() {
    let marker = Path::new(env!("CARGO_TARGET_TMPDIR")).join("browser-test-skipped");
    std::fs::remove_file(&marker).ok();
    if !installed("chromium") || !installed("chromedriver") {
        let why =
            "Chromium or ChromeDriver is not installed (apt-get install chromium chromium-driver)";
        skipped(&marker, "tests/browser.rs", why);
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = dir.path().join("cbox.canopy");
    convert(&scene("cbox.glb"), &archive, None);
    let view = dir.path().join("cbox.relight");
    let size = ["--width", "64", "--height", "64"];
    ok(&[
        &["--quiet", "relight", s(&archive), "-o", s(&view)],
        &size[..],
    ]
    .concat());
    let (_server, at) = relight_server(&view);
    let url = format!("http://{at}/");
    let port = 21000 + (std::process::id() % 20000) as u16;
    let driver = Command::new("chromedriver")
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let _driver = Killed(driver);
    let start = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "ChromeDriver did not start"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let profile = dir.path().join("chromium-profile");
    let args = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--window-size=800,600",
    ];
    let mut args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
    args.push(format!("--user-data-dir={}", profile.display()));
    let caps = json!({"capabilities": {"alwaysMatch": {"browserName": "chrome",
        "goog:chromeOptions": {"binary": "/usr/bin/chromium", "args": args}}}});
    let session = webdriver(port, "POST", "/session", Some(caps))["sessionId"]
        .as_str()
        .unwrap()
        .to_string();
    let sp = format!("/session/{session}");
    webdriver(
        port,
        "POST",
        &format!("{sp}/url"),
        Some(json!({"url": url})),
    );
    // Loaded, and refined to the whole image: a frame still refining would be followed by
    // the next slice's, which a click's new image could not be told from.
    let loaded = "const v = document.getElementById('view'); \
                  const s = document.getElementById('status').textContent; \
                  return v.complete && v.naturalWidth == 64 && v.src.startsWith('blob:') && \
                  s.includes('ms of compute') && !s.includes('refining');";
    wait_for(port, &session, loaded, "the page showed no relit image");
    let find = |css: &str| {
        let found = webdriver(
            port,
            "POST",
            &format!("{sp}/element"),
            Some(json!({"using": "css selector", "value": css})),
        );
        found
            .as_object()
            .unwrap()
            .values()
            .next()
            .unwrap()
            .as_str()
            .unwrap()
            .to_string()
    };
    let img = find("#view");
    let before = shown_red(port, &session, &img);
    let first = webdriver(
        port,
        "POST",
        &format!("{sp}/execute/sync"),
        Some(json!({"script": "return document.getElementById('view').src;", "args": []})),
    );
    // The first range input is the lamp's strength (0 to 4, at 1): a click at its middle
    // sets 2, which the page renders as a new image.
    let slider = find("input[type=range]");
    webdriver(
        port,
        "POST",
        &format!("{sp}/element/{slider}/click"),
        Some(json!({})),
    );
    let changed = format!(
        "const v = document.getElementById('view'); \
         const s = document.getElementById('status').textContent; \
         return v.complete && v.src != {first} && s.includes('ms of compute') && \
         !s.includes('refining');"
    );
    wait_for(
        port,
        &session,
        &changed,
        "no new image after the slider moved",
    );
    let after = shown_red(port, &session, &img);
    webdriver(port, "DELETE", &sp, None);
    eprintln!("mean red shown: {before:.1} at strength 1, {after:.1} after the click");
    // Twice the light is about 2^(1/2.2) = 1.37 times the 8-bit sRGB values shown.
    assert!(
        after > 1.2 * before,
        "the lamp at twice its strength: mean red {after:.1} against {before:.1}"
    );
}
