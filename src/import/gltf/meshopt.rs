//! EXT_meshopt_compression: buffer views whose bytes are meshoptimizer's vertex or index
//! codec output in another buffer, decoded with meshoptimizer's own decoder (the `meshopt`
//! crate) when the file is loaded, and written where the view says, most often into a
//! "fallback" buffer that has no bytes of its own. The filters the extension names
//! (octahedral normals, quaternions, exponent-mantissa floats) are undone after decoding.
//! The decoders are meant for untrusted input: a stream shorter than its count needs is
//! an error, never a read past its end.

use super::buffer::Buffer;
use anyhow::{anyhow, bail, Result};
use gltf::json::Root;

pub(super) const MESHOPT: &str = "EXT_meshopt_compression";

/// The most bytes one compressed byte may decode to (the vertex codec's densest case, an
/// all-zero stream, is 64), so a declared count cannot make the importer allocate
/// without data behind it.
const MAX_RATIO: usize = 128;
/// Slack on that bound for the codec's fixed headers and tails.
const SLACK: usize = 1 << 16;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Mode {
    Attributes,
    Triangles,
    Indices,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Filter {
    None,
    Octahedral,
    Quaternion,
    Exponential,
}

/// One compressed view: where its stream is and where its decoded bytes go.
pub(super) struct Compressed {
    view: usize,
    /// The buffer and offset the decoded bytes go to (the view's own).
    target: (usize, usize),
    /// The buffer, offset and length of the stream.
    source: (usize, usize, usize),
    stride: usize,
    count: usize,
    mode: Mode,
    filter: Filter,
}

/// Per buffer, whether it is a fallback that holds no bytes of its own.
pub(super) fn fallback_buffers(json: &Root) -> Vec<bool> {
    json.buffers
        .iter()
        .map(|b| {
            b.uri.is_none()
                && b.extensions
                    .as_ref()
                    .and_then(|e| e.others.get(MESHOPT))
                    .and_then(|m| m.get("fallback"))
                    .and_then(|f| f.as_bool())
                    == Some(true)
        })
        .collect()
}

fn field(ext: &serde_json::Value, name: &str, default: Option<u64>) -> Result<usize> {
    match (ext.get(name), default) {
        (None, Some(d)) => Ok(d as usize),
        (Some(v), _) => v
            .as_u64()
            .and_then(|v| usize::try_from(v).ok())
            .ok_or_else(|| anyhow!("its {MESHOPT} {name} is {v}, not a count")),
        (None, None) => bail!("its {MESHOPT} extension has no {name}"),
    }
}

/// The compressed views of the file, each checked: a known mode and filter, a stride the
/// mode allows, the decoded bytes inside the view, and no more of them than the stream
/// could give.
pub(super) fn compressed_views(json: &Root) -> Result<Vec<Compressed>> {
    let mut out = Vec::new();
    for (i, v) in json.buffer_views.iter().enumerate() {
        let Some(ext) = v.extensions.as_ref().and_then(|e| e.others.get(MESHOPT)) else {
            continue;
        };
        let c = compressed(i, v, ext).map_err(|e| anyhow!("buffer view {i}: {e}"))?;
        out.push(c);
    }
    Ok(out)
}

fn compressed(
    i: usize,
    v: &gltf::json::buffer::View,
    ext: &serde_json::Value,
) -> Result<Compressed> {
    let text = |name: &str, default: &str| -> String {
        ext.get(name)
            .and_then(|m| m.as_str())
            .unwrap_or(default)
            .to_string()
    };
    let mode = match text("mode", "").as_str() {
        "ATTRIBUTES" => Mode::Attributes,
        "TRIANGLES" => Mode::Triangles,
        "INDICES" => Mode::Indices,
        m => bail!("{MESHOPT} mode {m:?} is not ATTRIBUTES, TRIANGLES or INDICES"),
    };
    let filter = match text("filter", "NONE").as_str() {
        "NONE" => Filter::None,
        "OCTAHEDRAL" => Filter::Octahedral,
        "QUATERNION" => Filter::Quaternion,
        "EXPONENTIAL" => Filter::Exponential,
        f => bail!("{MESHOPT} filter {f:?} is not one Canopy decodes"),
    };
    let stride = field(ext, "byteStride", None)?;
    let count = field(ext, "count", None)?;
    let strides_ok = match (mode, filter) {
        (Mode::Attributes, Filter::None | Filter::Exponential) => {
            stride % 4 == 0 && (4..=256).contains(&stride)
        }
        (Mode::Attributes, Filter::Octahedral) => stride == 4 || stride == 8,
        (Mode::Attributes, Filter::Quaternion) => stride == 8,
        (_, Filter::None) => stride == 2 || stride == 4,
        _ => false,
    };
    if !strides_ok {
        bail!("{MESHOPT} byteStride {stride} does not suit mode {mode:?} with filter {filter:?}");
    }
    if mode == Mode::Triangles && count % 3 != 0 {
        bail!("{MESHOPT} TRIANGLES count {count} is not a multiple of 3");
    }
    let source = (
        field(ext, "buffer", None)?,
        field(ext, "byteOffset", Some(0))?,
        field(ext, "byteLength", None)?,
    );
    let decoded = count
        .checked_mul(stride)
        .ok_or_else(|| anyhow!("{count} elements of {stride} bytes"))?;
    if decoded > v.byte_length.0 as usize {
        bail!(
            "decodes to {decoded} bytes, more than its {} bytes",
            v.byte_length.0
        );
    }
    if decoded > source.2.saturating_mul(MAX_RATIO).saturating_add(SLACK) {
        bail!(
            "declares {decoded} decoded bytes from {} compressed ones, more than the codec can give",
            source.2
        );
    }
    Ok(Compressed {
        view: i,
        target: (v.buffer.value(), v.byte_offset.map_or(0, |o| o.0 as usize)),
        source,
        stride,
        count,
        mode,
        filter,
    })
}

/// The bytes a fallback buffer of `declared` bytes may hold: what the views writing to it
/// can decode to. A larger declaration is refused rather than allocated.
pub(super) fn fallback_bytes(
    views: &[Compressed],
    buffer: usize,
    declared: u64,
) -> Result<Vec<u8>> {
    let fill: usize = views
        .iter()
        .filter(|c| c.target.0 == buffer)
        .map(|c| c.count * c.stride)
        .sum();
    if declared > fill as u64 {
        bail!("{MESHOPT} fallback buffer {buffer} declares {declared} bytes; its compressed views decode to {fill}");
    }
    Ok(vec![0u8; declared as usize])
}

/// Decodes every compressed view into its place.
pub(super) fn decode(views: &[Compressed], buffers: &mut [Buffer]) -> Result<()> {
    for c in views {
        let bytes = decode_view(c, buffers).map_err(|e| anyhow!("buffer view {}: {e}", c.view))?;
        let (b, at) = c.target;
        let dst = buffers
            .get_mut(b)
            .and_then(|d| d.owned().get_mut(at..at.checked_add(bytes.len())?))
            .ok_or_else(|| anyhow!("buffer view {} lies outside buffer {b}", c.view))?;
        dst.copy_from_slice(&bytes);
    }
    Ok(())
}

fn decode_view(c: &Compressed, buffers: &[Buffer]) -> Result<Vec<u8>> {
    use meshopt::ffi;
    let (b, at, len) = c.source;
    let src = buffers
        .get(b)
        .and_then(|d| d.get(at..at.checked_add(len)?))
        .ok_or_else(|| anyhow!("its {MESHOPT} stream lies outside buffer {b}"))?;
    let mut out = vec![0u8; c.count * c.stride];
    let dst = out.as_mut_ptr().cast();
    // SAFETY: `out` holds count × stride bytes, the decoders write no more, and they read
    // no more than `src.len()` bytes of `src`.
    let code = unsafe {
        match c.mode {
            Mode::Attributes => {
                ffi::meshopt_decodeVertexBuffer(dst, c.count, c.stride, src.as_ptr(), src.len())
            }
            Mode::Triangles => {
                ffi::meshopt_decodeIndexBuffer(dst, c.count, c.stride, src.as_ptr(), src.len())
            }
            Mode::Indices => {
                ffi::meshopt_decodeIndexSequence(dst, c.count, c.stride, src.as_ptr(), src.len())
            }
        }
    };
    if code != 0 {
        bail!("its {MESHOPT} stream does not decode (meshoptimizer error {code})");
    }
    // SAFETY: the filters rewrite `count` elements of `stride` bytes in place; the stride
    // suits the filter (`compressed` checked it).
    unsafe {
        match c.filter {
            Filter::None => {}
            Filter::Octahedral => ffi::meshopt_decodeFilterOct(dst, c.count, c.stride),
            Filter::Quaternion => ffi::meshopt_decodeFilterQuat(dst, c.count, c.stride),
            Filter::Exponential => ffi::meshopt_decodeFilterExp(dst, c.count, c.stride),
        }
    }
    Ok(out)
}
