//! `canopy relight VIEW.relight --serve ADDR`: one local web page with a control per light
//! that shows the relit image as the controls move. `GET /` is the page, `GET /lights` the
//! archive's lights as JSON (what the page builds its controls from), `POST /render` takes a
//! light set as JSON (the TOML file's tables as objects) and answers a PNG, with the
//! relight's compute time in `X-Frame-Seconds` and `X-Frame-Complete: 0` while a light
//! moved or added is traced only in part (the page asks again for the next slice). A bad request gets a 4xx answer saying why;
//! the server goes on.

use super::Relighter;
use crate::light::LightSet;
use anyhow::{bail, Context, Result};
use canopy_format::name_str;
use std::io::Read;
use std::net::SocketAddr;
use tiny_http::{Header, Method, Request, Response, Server};

/// Largest light set accepted, in bytes.
const MAX_BODY: usize = 1 << 20;

const PAGE: &str = include_str!("page.html");

/// Serves `r` at `addr` (a loopback address) until the process ends; `ready` is told the
/// address bound (port 0 picks a free one).
pub fn serve(mut r: Relighter, addr: &str, ready: impl FnOnce(SocketAddr)) -> Result<()> {
    let at: SocketAddr = addr
        .parse()
        .with_context(|| format!("--serve {addr}: not an address (e.g. 127.0.0.1:8080)"))?;
    if !at.ip().is_loopback() {
        bail!("--serve {addr}: only a loopback address (127.0.0.1, ::1) is served; the page controls this machine's renderer");
    }
    let server = Server::http(at).map_err(|e| anyhow::anyhow!("--serve {addr}: {e}"))?;
    let bound = server
        .server_addr()
        .to_ip()
        .context("the server has no IP address")?;
    ready(bound);
    let lights = describe(&r);
    for req in server.incoming_requests() {
        let answer = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            answer(&mut r, &lights, req)
        }));
        if answer.is_err() {
            eprintln!("error: a request failed unexpectedly; the server goes on");
        }
    }
    Ok(())
}

fn text(code: u16, msg: &str) -> Response<std::io::Cursor<Vec<u8>>> {
    Response::from_string(format!("{msg}\n"))
        .with_status_code(code)
        .with_header(header("Content-Type", "text/plain; charset=utf-8"))
}

fn header(k: &str, v: &str) -> Header {
    Header::from_bytes(k.as_bytes(), v.as_bytes()).expect("ASCII header")
}

fn answer(r: &mut Relighter, lights: &str, mut req: Request) {
    let reply = match (req.method(), req.url()) {
        (Method::Get, "/") => Response::from_string(PAGE)
            .with_header(header("Content-Type", "text/html; charset=utf-8")),
        (Method::Get, "/lights") => {
            Response::from_string(lights).with_header(header("Content-Type", "application/json"))
        }
        (Method::Post, "/render") => render(r, &mut req),
        (_, "/" | "/lights" | "/render") => text(405, "method not allowed"),
        (_, url) => text(404, &format!("{url}: no such page (/, /lights, /render)")),
    };
    if let Err(e) = req.respond(reply) {
        eprintln!("error: answering a request: {e}");
    }
}

/// A light set's image, or why there is none.
fn render(r: &mut Relighter, req: &mut Request) -> Response<std::io::Cursor<Vec<u8>>> {
    let mut body = Vec::new();
    let read = req
        .as_reader()
        .take(MAX_BODY as u64 + 1)
        .read_to_end(&mut body);
    if read.is_err() {
        return text(400, "the request's body could not be read");
    }
    if body.len() > MAX_BODY {
        return text(413, &format!("a light set is at most {MAX_BODY} bytes"));
    }
    let Ok(body) = std::str::from_utf8(&body) else {
        return text(400, "the light set is not UTF-8");
    };
    let frame = LightSet::from_json(body, "the light set sent")
        .and_then(|set| r.set_lights(&set))
        .and_then(|note| Ok((r.frame()?, note)));
    let (f, note) = match frame {
        Ok(x) => x,
        Err(e) => return text(400, &format!("{e:#}")),
    };
    match f.image.png_bytes(1.0) {
        Ok(png) => {
            let mut resp = Response::from_data(png)
                .with_header(header("Content-Type", "image/png"))
                .with_header(header("X-Frame-Seconds", &format!("{:.4}", f.total())))
                .with_header(header(
                    "X-Frame-Complete",
                    if f.complete { "1" } else { "0" },
                ));
            if let Some(n) = note {
                resp = resp.with_header(header("X-Note", &n));
            }
            resp
        }
        Err(e) => text(500, &format!("{e:#}")),
    }
}

/// The archive's lamps (emissive materials), punctual lights and whether the view has an
/// environment, and its bounds, as JSON.
fn describe(r: &Relighter) -> String {
    let (materials, lights) = r.own_records();
    let lamps: Vec<serde_json::Value> = materials
        .iter()
        .enumerate()
        .filter(|(_, m)| m.emission.iter().any(|&v| v > 0.0))
        .map(|(i, m)| serde_json::json!({"material": i, "name": name_str(&m.name)}))
        .collect();
    let kinds = ["point", "spot", "directional"];
    let punctual: Vec<serde_json::Value> = lights
        .iter()
        .enumerate()
        .map(|(i, l)| {
            serde_json::json!({
                "light": i, "name": name_str(&l.name),
                "type": kinds.get(l.kind as usize).copied().unwrap_or("point"),
                "position": l.position, "direction": l.direction,
                "intensity": l.intensity, "color": l.color,
            })
        })
        .collect();
    let h = &r.setup.scene.cache.archive.header;
    serde_json::json!({
        "emitter": lamps, "light": punctual, "environment": r.has_environment(),
        "bounds": [h.bounds_min, h.bounds_max],
        "size": [r.file.header.width, r.file.header.height],
    })
    .to_string()
}
