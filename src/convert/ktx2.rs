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
    check_container(bytes, limit)?;
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

/// The level index checked before the transcoder sees it: every level inside the file, and
/// none declaring more decompressed bytes than its texels can fill (16 bytes a 4 × 4
/// block, the most any Basis format takes) or than `limit`, as the transcoder allocates
/// what a level declares. Read by hand from the fixed layout of KTX2 §3 (the `ktx2` crate's
/// reader panics on some damaged descriptors).
fn check_container(bytes: &[u8], limit: u64) -> Result<()> {
    let u32_at = |at: usize| -> Option<u64> {
        Some(u32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?) as u64)
    };
    let u64_at = |at: usize| -> Option<u64> {
        Some(u64::from_le_bytes(bytes.get(at..at + 8)?.try_into().ok()?))
    };
    let short = || anyhow!("the KTX2 header is cut short");
    let field = |at: usize| u32_at(at).ok_or_else(short);
    let (w, h) = (field(20)?, field(24)?);
    let images = [field(28)?, field(32)?, field(36)?]
        .iter()
        .map(|&n| n.max(1) as u128)
        .product::<u128>();
    for i in 0..field(40)?.max(1) {
        let at = 80 + 24 * i as usize;
        let (offset, length, unpacked) = (
            u64_at(at).ok_or_else(short)?,
            u64_at(at + 8).ok_or_else(short)?,
            u64_at(at + 16).ok_or_else(short)?,
        );
        if offset as u128 + length as u128 > bytes.len() as u128 {
            bail!("KTX2 level {i} lies past the file's end");
        }
        let side = |s: u64| (s.max(1) >> i.min(63)).max(1).div_ceil(4) as u128;
        let most = (16 * side(w) * side(h) * images).min(limit as u128);
        if unpacked as u128 > most {
            bail!("KTX2 level {i} declares {unpacked} decompressed bytes; its texels fill at most {most}");
        }
    }
    Ok(())
}
