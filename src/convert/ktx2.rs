//! KTX2 textures with Basis Universal data (glTF's KHR_texture_basisu), transcoded to RGBA8
//! by `basisu`, a pure-Rust port of the reference Basis Universal transcoder (its output
//! checked against the C++ one byte for byte, by its authors). Level 0 is taken; the
//! archive builds its own MIP pyramid from it, as for every other image.

use anyhow::{anyhow, bail, Result};

/// The first bytes of every KTX2 file.
pub const MAGIC: [u8; 12] = [
    0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A,
];

/// The texels of a KTX2 file's level 0, refused when they would take more than `limit`
/// bytes (4 a texel, twice while transcoding).
pub fn decode(bytes: &[u8], limit: u64) -> Result<image::RgbaImage> {
    use basisu::{DecodeFlags, TargetFormat, Transcoder};
    let bad = |e: basisu::Error| anyhow!("not a readable KTX2 / Basis Universal image: {e:?}");
    let tex = Transcoder::new(bytes).map_err(bad)?;
    let (w, h) = tex.base_dimensions();
    if w as u64 * h as u64 * 8 > limit {
        bail!(
            "the KTX2 image is {w}×{h} texels, about {} MiB to transcode, more than the memory budget leaves ({} MiB)",
            (w as u64 * h as u64 * 8) >> 20,
            limit >> 20
        );
    }
    if tex.layer_count() > 1 || tex.face_count() > 1 {
        eprintln!(
            "warning: a KTX2 texture of {} layers and {} faces: only the first is read",
            tex.layer_count(),
            tex.face_count()
        );
    }
    let rgba = tex
        .transcode(0, TargetFormat::Rgba32, DecodeFlags::NONE)
        .map_err(bad)?;
    image::RgbaImage::from_raw(w, h, rgba)
        .ok_or_else(|| anyhow!("the KTX2 transcoder gave too few texels for {w}×{h}"))
}
