//! glTF materials: metallic-roughness with the KHR extensions Canopy models, their
//! texture sources and UV transforms.

use super::buffer::Buffer;
use super::files::{data_uri, relative_file, view_bytes};
use super::layers::layers;
use crate::import::{SceneDesc, TextureSource};
use anyhow::{anyhow, Context, Result};
use canopy_format::{name_bytes, MaterialRecord, TextureRecord};
use std::path::Path;

/// How a texture reads its texture coordinates: the set, then KHR_texture_transform's
/// matrix (translation · rotation · scale, rows of a 2×3 affine map).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct UvMap {
    pub(super) set: u32,
    pub(super) m: [[f32; 3]; 2],
}

/// Which glTF texture-coordinate sets a material's textures read, as the archive's two
/// streams (None: the stream is not read).
pub(super) type UvSets = [Option<u32>; 2];

/// The material record, its textures added to `scene`, and the texture-coordinate sets its
/// textures read. Each texture slot keeps its own set and KHR_texture_transform; the
/// archive stores two sets per vertex, so a texture reading a third is dropped, its factor
/// kept, and `notes` says so.
pub(super) fn material(
    m: &gltf::Material,
    (doc, unsourced): (&gltf::Document, &super::files::Unsourced),
    scene: &mut SceneDesc,
    buffers: &[Buffer],
    dir: &Path,
    notes: &mut Vec<String>,
) -> Result<(MaterialRecord, UvSets)> {
    let pbr = m.pbr_metallic_roughness();
    let sg = m.pbr_specular_glossiness();
    let strength = m.emissive_strength().unwrap_or(1.0);
    let spec = m.specular();
    let normal = m.normal_texture();
    let base_texture = pbr
        .base_color_texture()
        .or_else(|| sg.as_ref().and_then(|s| s.diffuse_texture()));
    let layers = layers(m, doc)?;
    let textured = base_texture.is_some()
        || pbr.metallic_roughness_texture().is_some()
        || m.emissive_texture().is_some()
        || normal.is_some()
        || layers.textures.iter().any(Option::is_some);
    let mut flags = 0;
    if m.double_sided() {
        flags |= MaterialRecord::DOUBLE_SIDED;
    }
    if textured {
        flags |= MaterialRecord::TEXTURED;
    }
    match m.alpha_mode() {
        gltf::material::AlphaMode::Mask => flags |= MaterialRecord::ALPHA_MASK,
        gltf::material::AlphaMode::Blend => flags |= MaterialRecord::ALPHA_BLEND,
        gltf::material::AlphaMode::Opaque => {}
    }
    pub(super) fn info(i: gltf::texture::Info<'_>) -> (Result<UvMap>, gltf::Texture<'_>) {
        (Ok(UvMap::of(&i)), i.texture())
    }
    let [coat, coat_roughness, sheen_color, sheen_roughness, coat_normal] = layers.textures;
    // In `MaterialRecord::SLOTS` order, with whether each is sRGB.
    let slots = [
        (base_texture.map(info), true),
        (pbr.metallic_roughness_texture().map(info), false),
        (m.emissive_texture().map(info), true),
        (
            normal.as_ref().map(|n| (UvMap::of_normal(n), n.texture())),
            false,
        ),
        (coat, false),
        (coat_roughness, false),
        (sheen_color, true),
        (sheen_roughness, false),
        (coat_normal, false),
    ];
    let mut textures = [MaterialRecord::NO_TEXTURE; MaterialRecord::SLOTS];
    let mut sets: UvSets = [None; 2];
    let mut uv_streams = 0u16;
    let mut uv_transforms = [MaterialRecord::IDENTITY_UV; MaterialRecord::SLOTS];
    for (slot, (found, srgb)) in slots.into_iter().enumerate() {
        let Some((map, texture)) = found else {
            continue;
        };
        if let Some((_, why)) = unsourced.iter().find(|u| u.0 == texture.index()) {
            notes.push(format!(
                "its {} texture (texture {}) is dropped and its factor kept: {why}",
                SLOT_NAMES[slot],
                texture.index()
            ));
            continue;
        }
        let map = map?;
        let stream = match sets.iter().position(|&s| s == Some(map.set)) {
            Some(k) => k,
            None => match sets.iter().position(Option::is_none) {
                Some(k) => {
                    sets[k] = Some(map.set);
                    k
                }
                None => {
                    notes.push(format!(
                        "its {} texture reads texture coordinates {} where its other textures read sets {:?}; Canopy stores two sets per vertex, so it is dropped and its factor kept",
                        SLOT_NAMES[slot], map.set, sets.map(Option::unwrap_or_default)
                    ));
                    continue;
                }
            },
        };
        uv_streams |= (stream as u16) << slot;
        uv_transforms[slot] = map.record();
        textures[slot] = scene.add_texture(texture_source(&texture, srgb, buffers, dir)?)?;
    }
    let [b, mr, e, n, c0, c1, s0, s1, cn] = textures;
    let rec = MaterialRecord {
        name: name_bytes(m.name().unwrap_or("")),
        base_color: pbr.base_color_factor(),
        emission: m.emissive_factor().map(|e| e * strength),
        metallic: pbr.metallic_factor(),
        roughness: pbr.roughness_factor(),
        ior: m.ior().unwrap_or(1.5),
        transmission: m
            .transmission()
            .map(|t| t.transmission_factor())
            .unwrap_or(0.0),
        specular: spec.as_ref().map(|s| s.specular_factor()).unwrap_or(1.0),
        specular_color: spec
            .as_ref()
            .map(|s| s.specular_color_factor())
            .unwrap_or([1.0; 3]),
        flags,
        textures: [b, mr, e, n],
        alpha_cutoff: m.alpha_cutoff().unwrap_or(0.5),
        // Finite with a normal texture, 0 without (a dropped one included).
        normal_scale: match textures[MaterialRecord::NORMAL] {
            MaterialRecord::NO_TEXTURE => 0.0,
            _ => normal.as_ref().map_or(0.0, |n| n.scale()),
        },
        clearcoat: layers.clearcoat,
        clearcoat_roughness: layers.clearcoat_roughness,
        sheen_color: layers.sheen_color,
        sheen_roughness: layers.sheen_roughness,
        layer_textures: [c0, c1, s0, s1],
        coat_normal_texture: cn,
        uv_streams,
        // Finite with a coat normal texture, 0 without (a dropped one included).
        coat_normal_scale: match cn {
            MaterialRecord::NO_TEXTURE => 0.0,
            _ => layers.coat_normal_scale,
        },
        uv_transforms,
        ..volume(m)
    };
    let rec = match sg {
        Some(sg) => specular_glossiness(rec, &sg, notes),
        None => rec,
    };
    Ok((if m.unlit() { unlit(rec, notes) } else { rec }, sets))
}

/// KHR_materials_volume's attenuation as a record's volume fields (the rest default): none
/// for a thin wall (thickness 0), an infinite distance, or a material that transmits
/// nothing (the volume is seen only through transmission). The thickness itself, a
/// rasterizer's stand-in for the mesh's depth, is not needed: rays measure the depth.
fn volume(m: &gltf::Material) -> MaterialRecord {
    let mut rec = <MaterialRecord as bytemuck::Zeroable>::zeroed();
    rec.attenuation_color = [1.0; 3];
    let transmits = m
        .transmission()
        .is_some_and(|t| t.transmission_factor() > 0.0);
    if let Some(v) = m
        .volume()
        .filter(|v| transmits && v.thickness_factor() > 0.0)
    {
        let d = v.attenuation_distance();
        if d.is_finite() && d > 0.0 {
            rec.attenuation_color = v.attenuation_color().map(|c| c.clamp(0.0, 1.0));
            rec.attenuation_distance = d;
        }
    }
    rec
}

/// KHR_materials_unlit as an emitter of its base colour (factor and texture) that reflects
/// nothing: seen directly it shows its base colour, as the extension asks, and, as a
/// renderer with no notion of "unlit" must choose, it also lights what faces it (as
/// Blender's importer makes it an emission shader). `notes` says so.
fn unlit(mut rec: MaterialRecord, notes: &mut Vec<String>) -> MaterialRecord {
    let [r, g, b, a] = rec.base_color;
    rec.emission = [r, g, b];
    let (base, emissive) = (MaterialRecord::BASE_COLOR, MaterialRecord::EMISSIVE);
    rec.textures[emissive] = rec.textures[base];
    rec.uv_transforms[emissive] = rec.uv_transforms[base];
    let stream = rec.slot_stream(base) as u16;
    rec.uv_streams = rec.uv_streams & !(1 << emissive) | stream << emissive;
    rec.base_color = [0.0, 0.0, 0.0, a];
    rec.metallic = 0.0;
    rec.specular = 0.0;
    rec.transmission = 0.0;
    notes.push("uses KHR_materials_unlit: shaded as an emitter of its base colour that reflects nothing, so it also lights its surroundings".into());
    rec
}

/// KHR_materials_pbrSpecularGlossiness as metallic-roughness with KHR_materials_specular:
/// the diffuse colour as base colour (dielectric, metallic 0), roughness 1 − glossiness,
/// and the specular colour as F0 through the specular colour factor (F0 = 0.04 × factor at
/// ior 1.5, clamped at 1 where shaded). The specular-glossiness texture has no slot: it is
/// dropped, its factors kept, and `notes` says so.
fn specular_glossiness(
    mut rec: MaterialRecord,
    sg: &gltf::material::PbrSpecularGlossiness,
    notes: &mut Vec<String>,
) -> MaterialRecord {
    rec.base_color = sg.diffuse_factor();
    rec.metallic = 0.0;
    rec.roughness = 1.0 - sg.glossiness_factor();
    rec.ior = 1.5;
    rec.specular = 1.0;
    rec.specular_color = sg.specular_factor().map(|f| f / 0.04);
    let mut note = "uses KHR_materials_pbrSpecularGlossiness: shaded as metallic-roughness (diffuse as base colour, roughness 1 − glossiness, specular as F0)".to_string();
    if sg.specular_glossiness_texture().is_some() {
        note += "; its specularGlossinessTexture is dropped, its factors kept";
    }
    notes.push(note);
    rec
}

/// The texture slots' names, in `MaterialRecord::SLOTS` order.
const SLOT_NAMES: [&str; 9] = [
    "base colour",
    "metallic-roughness",
    "emissive",
    "normal",
    "clearcoat",
    "clearcoat roughness",
    "sheen colour",
    "sheen roughness",
    "clearcoat normal",
];

/// Where a glTF texture's image is: a buffer view, a data URI or a file beside the glTF.
pub(super) fn texture_source(
    t: &gltf::Texture,
    srgb: bool,
    buffers: &[Buffer],
    dir: &Path,
) -> Result<TextureSource> {
    use gltf::texture::WrappingMode;
    let wrap = |w: WrappingMode| match w {
        WrappingMode::Repeat => TextureRecord::WRAP_REPEAT,
        WrappingMode::ClampToEdge => TextureRecord::WRAP_CLAMP,
        WrappingMode::MirroredRepeat => TextureRecord::WRAP_MIRROR,
    };
    let sampler = t.sampler();
    let image = t.source();
    let mut src = TextureSource {
        file: None,
        bytes: None,
        name: image.name().unwrap_or("").to_string(),
        srgb,
        wrap: [wrap(sampler.wrap_s()), wrap(sampler.wrap_t())],
    };
    match image.source() {
        gltf::image::Source::View { view, .. } => {
            let data = view_bytes(&view, buffers).ok_or_else(|| {
                anyhow!(
                    "image {}: its buffer view lies outside its buffer",
                    image.index()
                )
            })?;
            src.bytes = Some(std::sync::Arc::new(data.to_vec()));
            if src.name.is_empty() {
                src.name = format!("image {}", image.index());
            }
        }
        gltf::image::Source::Uri { uri, .. } if uri.starts_with("data:") => {
            let data = data_uri(uri).map_err(|e| anyhow!("image {}: {e}", image.index()))?;
            src.bytes = Some(std::sync::Arc::new(data));
            if src.name.is_empty() {
                src.name = format!("image {}", image.index());
            }
        }
        gltf::image::Source::Uri { uri, .. } => {
            let name = relative_file(uri).map_err(|e| anyhow!("image {}: {e}", image.index()))?;
            src.name = name.rsplit('/').next().unwrap_or(&name).to_string();
            src.file = Some(dir.join(&name));
        }
    }
    Ok(src)
}

impl UvMap {
    pub(super) fn of(info: &gltf::texture::Info) -> UvMap {
        match info.texture_transform() {
            Some(t) => UvMap::new(
                t.tex_coord().unwrap_or(info.tex_coord()),
                t.offset(),
                t.rotation(),
                t.scale(),
            ),
            None => UvMap::new(info.tex_coord(), [0.0; 2], 0.0, [1.0; 2]),
        }
    }

    /// The gltf crate gives a normal texture's KHR_texture_transform only as JSON.
    pub(super) fn of_normal(n: &gltf::material::NormalTexture) -> Result<UvMap> {
        let transform = n.extension_value("KHR_texture_transform");
        UvMap::from_json(n.tex_coord(), transform, "normalTexture")
    }

    /// Texture coordinate set `set` under a KHR_texture_transform given as JSON, of the
    /// texture named `what`.
    pub(super) fn from_json(
        set: u32,
        transform: Option<&serde_json::Value>,
        what: &str,
    ) -> Result<UvMap> {
        use gltf::json::extensions::texture::TextureTransform;
        Ok(match transform {
            Some(v) => {
                let t: TextureTransform = serde_json::from_value(v.clone())
                    .with_context(|| format!("{what}'s KHR_texture_transform"))?;
                UvMap::new(
                    t.tex_coord.unwrap_or(set),
                    t.offset.0,
                    t.rotation.0,
                    t.scale.0,
                )
            }
            None => UvMap::new(set, [0.0; 2], 0.0, [1.0; 2]),
        })
    }

    /// KHR_texture_transform: translation · rotation · scale.
    pub(super) fn new(set: u32, [ox, oy]: [f32; 2], r: f32, [sx, sy]: [f32; 2]) -> UvMap {
        let (s, c) = r.sin_cos();
        UvMap {
            set,
            m: [[c * sx, s * sy, ox], [-s * sx, c * sy, oy]],
        }
    }

    /// The map as a material record stores it (`MaterialRecord::uv_transforms`).
    fn record(&self) -> [f32; 6] {
        let [[a, b, c], [d, e, f]] = self.m;
        [a, b, c, d, e, f]
    }
}
