//! KHR_materials_clearcoat and KHR_materials_sheen, which the gltf crate does not model:
//! read from the material's extension JSON.

use super::material::UvMap;
use anyhow::{anyhow, bail, Result};
use canopy_format::MaterialRecord;
use serde_json::Value;

pub(super) const CLEARCOAT: &str = "KHR_materials_clearcoat";
pub(super) const SHEEN: &str = "KHR_materials_sheen";

/// A textureInfo's texture and how it reads its texture coordinates.
pub(super) type TextureInfo<'a> = Option<(Result<UvMap>, gltf::Texture<'a>)>;

/// A material's coat and sheen factors, and the textures of their slots
/// (`MaterialRecord::CLEARCOAT`…, then the coat's normal texture) with how each reads its
/// texture coordinates.
pub(super) struct Layers<'a> {
    pub(super) clearcoat: f32,
    pub(super) clearcoat_roughness: f32,
    pub(super) sheen_color: [f32; 3],
    pub(super) sheen_roughness: f32,
    pub(super) textures: [TextureInfo<'a>; 5],
    /// clearcoatNormalTexture.scale (1 when it has none).
    pub(super) coat_normal_scale: f32,
}

/// The layers of material `m` of `doc` (none: zero factors, no textures).
pub(super) fn layers<'a>(m: &gltf::Material<'a>, doc: &'a gltf::Document) -> Result<Layers<'a>> {
    let mut out = Layers {
        clearcoat: 0.0,
        clearcoat_roughness: 0.0,
        sheen_color: [0.0; 3],
        sheen_roughness: 0.0,
        textures: [None, None, None, None, None],
        coat_normal_scale: 1.0,
    };
    if let Some(c) = m.extension_value(CLEARCOAT) {
        out.clearcoat = factor(c, "clearcoatFactor", 0.0)?;
        out.clearcoat_roughness = factor(c, "clearcoatRoughnessFactor", 0.0)?;
        out.textures[MaterialRecord::CLEARCOAT] = texture(c, "clearcoatTexture", doc)?;
        out.textures[MaterialRecord::CLEARCOAT_ROUGHNESS] =
            texture(c, "clearcoatRoughnessTexture", doc)?;
        out.textures[4] = texture(c, "clearcoatNormalTexture", doc)?;
        if let Some(v) = c.get("clearcoatNormalTexture").and_then(|t| t.get("scale")) {
            out.coat_normal_scale = v
                .as_f64()
                .map(|x| x as f32)
                .filter(|x| x.is_finite())
                .ok_or_else(|| anyhow!("clearcoatNormalTexture.scale {v} is not a number"))?;
        }
    }
    if let Some(s) = m.extension_value(SHEEN) {
        out.sheen_color = match s.get("sheenColorFactor") {
            None => [0.0; 3],
            Some(v) => {
                let rgb: Vec<f64> = serde_json::from_value(v.clone())
                    .map_err(|_| anyhow!("sheenColorFactor {v} is not three numbers"))?;
                match rgb[..] {
                    [r, g, b] => [r, g, b].map(|c| c as f32),
                    _ => bail!("sheenColorFactor {v} is not three numbers"),
                }
            }
        };
        if let Some(c) = out.sheen_color.iter().find(|c| !(0.0..=1.0).contains(*c)) {
            bail!("sheenColorFactor has {c}, outside [0, 1]");
        }
        out.sheen_roughness = factor(s, "sheenRoughnessFactor", 0.0)?;
        out.textures[MaterialRecord::SHEEN_COLOR] = texture(s, "sheenColorTexture", doc)?;
        out.textures[MaterialRecord::SHEEN_ROUGHNESS] = texture(s, "sheenRoughnessTexture", doc)?;
    }
    Ok(out)
}

/// A factor in [0, 1] (`default` when absent).
fn factor(ext: &Value, key: &str, default: f32) -> Result<f32> {
    let Some(v) = ext.get(key) else {
        return Ok(default);
    };
    match v.as_f64() {
        Some(x) if (0.0..=1.0).contains(&x) => Ok(x as f32),
        _ => bail!("{key} {v} is not a number in [0, 1]"),
    }
}

/// A textureInfo of the extension: its texture and how it reads texture coordinates.
fn texture<'a>(ext: &Value, key: &str, doc: &'a gltf::Document) -> Result<TextureInfo<'a>> {
    let Some(info) = ext.get(key) else {
        return Ok(None);
    };
    let index = info.get("index").and_then(Value::as_u64);
    let count = doc.textures().len();
    let Some(t) = index.and_then(|i| doc.textures().nth(i as usize)) else {
        bail!(
            "{key} names texture {} of {count}",
            info.get("index").unwrap_or(&Value::Null)
        );
    };
    let set = info.get("texCoord").and_then(Value::as_u64).unwrap_or(0) as u32;
    let transform = info
        .get("extensions")
        .and_then(|e| e.get("KHR_texture_transform"));
    Ok(Some((UvMap::from_json(set, transform, key), t)))
}
