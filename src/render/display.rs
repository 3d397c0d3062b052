//! `--display-server HOST:PORT`: the image streamed to tev (the viewer pbrt-v4 and Mitsuba
//! users watch renders converge in) as it converges, over tev's IPC protocol: packets of a
//! little-endian u32 length (itself included), a type byte and the payload; `CreateImage`
//! (4) once, then `UpdateImage` (6, its third version) in tiles of at most 128², RGB
//! interleaved. The packets are byte for byte what tev's own Python client (`tevclient`
//! 1.0.4) writes (a unit test holds its bytes).

use crate::image::Image;
use anyhow::{Context, Result};
use std::io::Write;
use std::net::TcpStream;
use std::time::{Duration, Instant};

const CREATE_IMAGE: u8 = 4;
const UPDATE_IMAGE: u8 = 6;
/// Side of the tiles an update is sent in (tevclient's).
const TILE: u32 = 128;
/// Least time between two updates while rendering.
const EVERY: Duration = Duration::from_millis(500);

pub struct Display {
    address: String,
    stream: Option<TcpStream>,
    name: String,
    last: Option<Instant>,
}

impl Display {
    /// Connects to tev at `address` and creates an image `name` of the frame's size.
    pub fn connect(address: &str, name: &str, [width, height]: [u32; 2]) -> Result<Display> {
        let mut stream = TcpStream::connect(address).with_context(|| {
            format!("--display-server {address}: cannot connect (is tev running, e.g. `tev --hostname {address}`?)")
        })?;
        stream
            .write_all(&create_image(name, width, height))
            .with_context(|| format!("--display-server {address}: the connection failed"))?;
        Ok(Display {
            address: address.to_string(),
            stream: Some(stream),
            name: name.to_string(),
            last: None,
        })
    }

    /// Sends the image `img` makes, a window of the frame at `origin`, unless one was sent
    /// less than `EVERY` ago and `last` is false. A broken connection ends the streaming
    /// with a warning; the render goes on.
    pub fn update(&mut self, img: impl FnOnce() -> Image, origin: [u32; 2], last: bool) {
        if !last && self.last.is_some_and(|t| t.elapsed() < EVERY) {
            return;
        }
        let Some(stream) = &mut self.stream else {
            return;
        };
        self.last = Some(Instant::now());
        let img = &img();
        let sent = tiles(img).try_for_each(|[x, y, w, h]| {
            stream.write_all(&update_image(&self.name, img, [x, y, w, h], origin))
        });
        if let Err(e) = sent {
            eprintln!(
                "warning: --display-server {}: {e}; the render goes on without it",
                self.address
            );
            self.stream = None;
        }
    }
}

/// The image's tiles as x, y, width, height.
fn tiles(img: &Image) -> impl Iterator<Item = [u32; 4]> + '_ {
    (0..img.height).step_by(TILE as usize).flat_map(move |y| {
        (0..img.width)
            .step_by(TILE as usize)
            .map(move |x| [x, y, TILE.min(img.width - x), TILE.min(img.height - y)])
    })
}

/// A packet: its length, type and payload.
fn packet(kind: u8, payload: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let mut p = vec![0, 0, 0, 0, kind];
    payload(&mut p);
    let len = p.len() as u32;
    p[..4].copy_from_slice(&len.to_le_bytes());
    p
}

fn string(p: &mut Vec<u8>, s: &str) {
    p.extend(s.bytes());
    p.push(0);
}

const CHANNELS: [&str; 3] = ["R", "G", "B"];

fn create_image(name: &str, width: u32, height: u32) -> Vec<u8> {
    packet(CREATE_IMAGE, |p| {
        p.push(0); // no focus grab
        string(p, name);
        for v in [width as i32, height as i32, CHANNELS.len() as i32] {
            p.extend(v.to_le_bytes());
        }
        CHANNELS.iter().for_each(|c| string(p, c));
    })
}

/// The tile x, y, w, h of `img`, placed at `origin` in the frame.
fn update_image(name: &str, img: &Image, [x, y, w, h]: [u32; 4], origin: [u32; 2]) -> Vec<u8> {
    packet(UPDATE_IMAGE, |p| {
        p.push(0);
        string(p, name);
        p.extend((CHANNELS.len() as i32).to_le_bytes());
        CHANNELS.iter().for_each(|c| string(p, c));
        for v in [origin[0] + x, origin[1] + y, w, h] {
            p.extend((v as i32).to_le_bytes());
        }
        // Channel c at offset c, stride 3: interleaved RGB.
        for k in 0..3i64 {
            p.extend(k.to_le_bytes());
        }
        for _ in 0..3 {
            p.extend(3i64.to_le_bytes());
        }
        for row in y..y + h {
            let at = (row * img.width + x) as usize;
            for px in &img.pixels[at..at + w as usize] {
                px.iter().for_each(|v| p.extend(v.to_le_bytes()));
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// tevclient 1.0.4's `packet.create_image("canopy", 3, 2, ["R", "G", "B"], False)` and
    /// `packet.update_image("canopy", [[[1, 2, 3], [0.5, 0.25, 0.125]]], ["R", "G", "B"],
    /// 1, 1, False)`, byte for byte.
    #[test]
    fn packets_are_what_tevs_own_client_writes() {
        let create = [
            31, 0, 0, 0, 4, 0, 99, 97, 110, 111, 112, 121, 0, 3, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0,
            82, 0, 71, 0, 66, 0,
        ];
        assert_eq!(create_image("canopy", 3, 2), create);
        let update: [u8; 111] = [
            111, 0, 0, 0, 6, 0, 99, 97, 110, 111, 112, 121, 0, 3, 0, 0, 0, 82, 0, 71, 0, 66, 0, 1,
            0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0,
            0, 0, 2, 0, 0, 0, 0, 0, 0, 0, 3, 0, 0, 0, 0, 0, 0, 0, 3, 0, 0, 0, 0, 0, 0, 0, 3, 0, 0,
            0, 0, 0, 0, 0, 0, 0, 128, 63, 0, 0, 0, 64, 0, 0, 64, 64, 0, 0, 0, 63, 0, 0, 128, 62, 0,
            0, 0, 62,
        ];
        let img = Image {
            width: 2,
            height: 1,
            pixels: vec![[1.0, 2.0, 3.0], [0.5, 0.25, 0.125]],
        };
        assert_eq!(update_image("canopy", &img, [0, 0, 2, 1], [1, 1]), update);
    }

    #[test]
    fn tiles_cover_the_image_once() {
        let img = Image::new(300, 130);
        let t: Vec<[u32; 4]> = tiles(&img).collect();
        assert_eq!(t.len(), 6);
        assert_eq!(t.iter().map(|[_, _, w, h]| w * h).sum::<u32>(), 300 * 130);
        assert_eq!(t[5], [256, 128, 44, 2]);
    }
}
