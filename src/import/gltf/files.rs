//! Reading a glTF file: the JSON or GLB container, its buffers (embedded, data URIs or
//! side files, each bounded) and the checks on images, primitives and accessors.

use super::buffer::Buffer;
use super::draco::{Vertices, DRACO};
use super::meshopt::{self, MESHOPT};
use anyhow::{anyhow, bail, Context, Result};
use std::path::Path;
use std::sync::Arc;

/// KHR_mesh_quantization: positions, normals and texture coordinates as 8- or 16-bit
/// integers (normalized or not), which `read_floats` reads.
const QUANTIZATION: &str = "KHR_mesh_quantization";

/// Largest external buffer or `.gltf` JSON read.
const MAX_SIDE_FILE: u64 = 16 << 30;

/// Parses the document (the gltf crate's validation runs after our own index checks, as
/// one of its hooks indexes accessors unchecked) and loads its buffers, each checked
/// against its declared length; a GLB's BIN chunk stays mapped from the file (`Buffer`).
/// Images are never read here: textures are read as they are stored. Also returns the
/// textures that have no image Canopy reads, with why (`unsourced_textures`).
pub(super) fn load(path: &Path) -> Result<(gltf::Document, Vec<Buffer>, Unsourced)> {
    if crate::import::check_regular(path, u64::MAX, "glTF file")?.len() == 0 {
        bail!(
            "{}: not a valid glTF file: the file is empty",
            path.display()
        );
    }
    let file = std::fs::File::open(path).map_err(crate::import::context(path))?;
    // SAFETY: a read-only private mapping; the file changing underneath during the import
    // is outside what Canopy guards against (as for every input it reads).
    let map = Arc::new(unsafe { memmap2::Mmap::map(&file) }.map_err(crate::import::context(path))?);
    let bad = |e: &dyn std::fmt::Display| anyhow!("{}: not a valid glTF file: {e}", path.display());
    let (json, mut blob) = match map.starts_with(b"glTF") {
        true => {
            let glb = gltf::binary::Glb::from_slice(&map).map_err(|e| bad(&e))?;
            let blob = glb.bin.as_deref().map(|bin| Buffer::Mapped {
                map: Arc::clone(&map),
                at: bin.as_ptr() as usize - map.as_ptr() as usize,
                len: bin.len(),
            });
            (glb.json.into_owned(), blob)
        }
        false => (map.to_vec(), None),
    };
    let g = gltf::Gltf::from_slice_without_validation(&json).map_err(|e| bad(&e))?;
    let mut json = g.document.into_json();
    // Quantized attributes are read here (`read_floats`), Draco and meshopt data decoded
    // here (`draco`, `meshopt`), not by the gltf crate, whose validation refuses them.
    if let Some(e) = json
        .extensions_required
        .iter()
        .find(|e| !READ.contains(&e.as_str()))
    {
        bail!(
            "{}: the file requires {e}, which Canopy does not read (its content cannot be rendered without it)",
            path.display()
        );
    }
    json.extensions_required
        .retain(|e| ![QUANTIZATION, DRACO, MESHOPT, WEBP, BASISU].contains(&e.as_str()));
    for (mi, m) in json.meshes.iter().enumerate() {
        for (pi, p) in m.primitives.iter().enumerate() {
            let refs = p.attributes.values().chain(p.indices.as_ref());
            if let Some(a) = refs.map(|a| a.value()).find(|&a| a >= json.accessors.len()) {
                bail!(
                    "{}: mesh {mi} primitive {pi} names accessor {a} of {}",
                    path.display(),
                    json.accessors.len()
                );
            }
        }
    }
    stand_in_views(&mut json);
    choose_image_sources(&mut json);
    let unsourced = unsourced_textures(&mut json);
    check_images(&json).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let fallback = meshopt::fallback_buffers(&json);
    let packed =
        meshopt::compressed_views(&json).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let doc = gltf::Document::from_json(json).map_err(|e| bad(&e))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut buffers =
        doc.buffers()
            .map(|b| match fallback[b.index()] {
                true => meshopt::fallback_bytes(&packed, b.index(), b.length() as u64)
                    .map(Buffer::Owned),
                false => load_buffer(&b, &mut blob, dir),
            })
            .collect::<Result<Vec<_>>>()
            .with_context(|| path.display().to_string())?;
    meshopt::decode(&packed, &mut buffers).with_context(|| path.display().to_string())?;
    Ok((doc, buffers, unsourced))
}

/// A Draco primitive's accessors have no buffer view, which the gltf crate's validation
/// refuses: each is given the primitive's Draco view to stand in. Nothing reads them
/// through it (`draco::decode` reads the primitive), and any other reader bounds-checks it.
fn stand_in_views(json: &mut gltf::json::Root) {
    for m in &json.meshes {
        for p in &m.primitives {
            let Some(view) = p
                .extensions
                .as_ref()
                .and_then(|e| e.others.get(DRACO))
                .and_then(|d| d.get("bufferView"))
                .and_then(|v| v.as_u64())
                .and_then(|v| u32::try_from(v).ok())
            else {
                continue;
            };
            for a in p.attributes.values().chain(p.indices.as_ref()) {
                if let Some(acc) = json.accessors.get_mut(a.value()) {
                    acc.buffer_view.get_or_insert(gltf::json::Index::new(view));
                }
            }
        }
    }
}

/// The extensions Canopy reads; any other is named when a file uses it, and a file that
/// requires one is refused.
pub(super) const READ: &[&str] = &[
    "KHR_lights_punctual",
    super::layers::CLEARCOAT,
    super::layers::SHEEN,
    "KHR_materials_emissive_strength",
    "KHR_materials_ior",
    "KHR_materials_specular",
    "KHR_materials_transmission",
    "KHR_materials_pbrSpecularGlossiness",
    "KHR_materials_unlit",
    "KHR_materials_volume",
    "KHR_texture_transform",
    "EXT_mesh_gpu_instancing",
    QUANTIZATION,
    DRACO,
    MESHOPT,
    WEBP,
    BASISU,
];

/// EXT_texture_webp: a texture's WebP image, which the importer decodes.
const WEBP: &str = "EXT_texture_webp";
/// KHR_texture_basisu: a texture's KTX2 image with Basis Universal data, transcoded.
const BASISU: &str = "KHR_texture_basisu";

/// Each texture's image, as glTF's fallback rules choose it: the image an extension
/// offers (WebP, then KTX2; the `source` is then a fallback, or absent), else its `source`.
fn choose_image_sources(json: &mut gltf::json::Root) {
    for t in &mut json.textures {
        let offered = |name: &str| {
            t.extensions
                .as_ref()
                .and_then(|e| e.others.get(name))
                .and_then(|w| w.get("source"))
                .and_then(|s| s.as_u64())
                .and_then(|s| u32::try_from(s).ok())
        };
        if let Some(image) = offered(WEBP).or_else(|| offered(BASISU)) {
            t.source = gltf::json::Index::new(image);
        }
    }
}

/// Textures with no image Canopy reads, by index, with why.
pub(super) type Unsourced = Vec<(usize, String)>;

/// Textures with no image Canopy reads: no `source` and no extension Canopy reads offering
/// one (glTF leaves that to extensions), or a `source` out of range. Each is pointed at a
/// stand-in image nothing reads (the gltf crate indexes images unchecked), and materials drop
/// them by name, keeping their factors (`material`).
fn unsourced_textures(json: &mut gltf::json::Root) -> Unsourced {
    let images = json.images.len();
    let mut out = Vec::new();
    for (i, t) in json.textures.iter_mut().enumerate() {
        let why = match t.source.value() {
            s if s < images => continue,
            s if s as u32 == u32::MAX => {
                "it has no image (no `source`, and no extension Canopy reads offers one)"
                    .to_string()
            }
            s => format!("it names image {s} of {images}"),
        };
        out.push((i, why));
        t.source = gltf::json::Index::new(images as u32);
    }
    if !out.is_empty() {
        json.images.push(gltf::json::Image {
            buffer_view: None,
            mime_type: None,
            name: None,
            uri: Some("data:,".to_string()),
            extensions: None,
            extras: Default::default(),
        });
    }
    out
}

/// Every texture's sampler exists (its image does, once `unsourced_textures` ran), and every
/// image names a buffer view in range with its MIME type, or a URI (the gltf crate's
/// accessors unwrap these).
fn check_images(json: &gltf::json::Root) -> Result<()> {
    for (i, t) in json.textures.iter().enumerate() {
        if let Some(s) = t.sampler.filter(|s| s.value() >= json.samplers.len()) {
            bail!(
                "texture {i} names sampler {} of {}",
                s.value(),
                json.samplers.len()
            );
        }
    }
    for (i, im) in json.images.iter().enumerate() {
        match (&im.buffer_view, &im.mime_type, &im.uri) {
            (Some(v), Some(_), _) if v.value() < json.buffer_views.len() => {}
            (Some(v), _, _) => bail!(
                "image {i}: buffer view {} of {} (with a MIME type) required",
                v.value(),
                json.buffer_views.len()
            ),
            (None, _, Some(_)) => {}
            (None, _, None) => bail!("image {i} has neither a URI nor a buffer view"),
        }
    }
    Ok(())
}

/// A buffer view's bytes, or None where it lies outside its buffer.
pub(super) fn view_bytes<'a>(view: &gltf::buffer::View, buffers: &'a [Buffer]) -> Option<&'a [u8]> {
    buffers
        .get(view.buffer().index())?
        .get(view.offset()..view.offset().checked_add(view.length())?)
}

/// The bytes of a base64 `data:` URI.
pub(super) fn data_uri(uri: &str) -> Result<Vec<u8>> {
    use base64::Engine;
    let (_, payload) = uri
        .split_once(";base64,")
        .ok_or_else(|| anyhow!("a data URI that is not base64"))?;
    base64::engine::general_purpose::STANDARD
        .decode(payload)
        .map_err(|e| anyhow!("bad base64 data: {e}"))
}

/// The file name a URI gives, percent-decoded; refused unless relative (no scheme).
pub(super) fn relative_file(uri: &str) -> Result<String> {
    let name = urlencoding::decode(uri).map_err(|_| anyhow!("URI {uri:?} is not UTF-8"))?;
    if name.contains(':') {
        bail!("URI {uri:?} is not a relative file name");
    }
    Ok(name.into_owned())
}

/// One buffer's bytes: the GLB BIN chunk (its length the declared one, padded by at most 3
/// bytes, as the GLB spec writes it; one buffer takes it), a base64 data URI, or a regular
/// file beside the glTF.
fn load_buffer(b: &gltf::Buffer, blob: &mut Option<Buffer>, dir: &Path) -> Result<Buffer> {
    let want = b.length();
    let i = b.index();
    let mut data = match b.source() {
        gltf::buffer::Source::Bin => {
            let Some(Buffer::Mapped { map, at, len }) = blob.take() else {
                bail!("buffer {i} refers to a missing BIN chunk (or another buffer took it)");
            };
            if len < want || len > want + 3 {
                bail!("buffer {i} declares {want} bytes, the BIN chunk holds {len}");
            }
            return Ok(Buffer::Mapped { map, at, len: want });
        }
        gltf::buffer::Source::Uri(uri) if uri.starts_with("data:") => {
            data_uri(uri).map_err(|e| anyhow!("buffer {i}: {e}"))?
        }
        gltf::buffer::Source::Uri(uri) => {
            let name = relative_file(uri).map_err(|e| anyhow!("buffer {i}: {e}"))?;
            crate::import::read_regular(&dir.join(&name), MAX_SIDE_FILE, "glTF buffer")?
        }
    };
    if data.len() < want {
        bail!("buffer {i} declares {want} bytes but holds {}", data.len());
    }
    data.truncate(want);
    Ok(Buffer::Owned(data))
}

/// The accessors a primitive's triangles are read from, checked before the gltf crate reads
/// them (`check_accessor`).
pub(super) fn check_primitive(prim: &gltf::Primitive, buffers: &[Buffer]) -> Result<()> {
    use gltf::accessor::{DataType, Dimensions};
    use gltf::Semantic;
    let mut wanted: Vec<(gltf::Accessor, &str, &[DataType], Dimensions)> = Vec::new();
    // F32, or the integers KHR_mesh_quantization allows.
    let vec3: &[DataType] = &[
        DataType::F32,
        DataType::I8,
        DataType::U8,
        DataType::I16,
        DataType::U16,
    ];
    for (sem, a) in prim.attributes() {
        match sem {
            Semantic::Positions => wanted.push((a, "POSITION", vec3, Dimensions::Vec3)),
            Semantic::Normals => wanted.push((a, "NORMAL", vec3, Dimensions::Vec3)),
            Semantic::TexCoords(_) => wanted.push((a, "TEXCOORD", vec3, Dimensions::Vec2)),
            _ => {}
        }
    }
    if let Some(a) = prim.indices() {
        let ints: &[DataType] = &[DataType::U8, DataType::U16, DataType::U32];
        wanted.push((a, "indices", ints, Dimensions::Scalar));
    }
    for (a, name, types, dims) in wanted {
        let what = format!("{name} accessor {}", a.index());
        check_accessor(&a, &what, types, dims, buffers)?;
    }
    Ok(())
}

/// An accessor checked before the gltf crate reads it: a type the spec allows, no sparse
/// storage, every element inside its buffer view and the view inside its buffer.
pub(super) fn check_accessor(
    a: &gltf::Accessor,
    what: &str,
    types: &[gltf::accessor::DataType],
    dims: gltf::accessor::Dimensions,
    buffers: &[Buffer],
) -> Result<()> {
    // Only integers may be normalized.
    let float = a.data_type() == gltf::accessor::DataType::F32;
    if !types.contains(&a.data_type()) || a.dimensions() != dims || (a.normalized() && float) {
        bail!(
            "{what} is {:?} {:?}{}, the spec requires {dims:?} of {types:?}",
            a.dimensions(),
            a.data_type(),
            if a.normalized() { " normalized" } else { "" }
        );
    }
    if let Some(sp) = a.sparse() {
        if a.dimensions() == gltf::accessor::Dimensions::Scalar {
            bail!("{what} is sparse, which Canopy reads only for vertex attributes");
        }
        check_sparse(a, &sp, buffers).map_err(|e| anyhow!("{what}: sparse storage: {e}"))?;
    }
    let Some(view) = a.view() else {
        return match a.sparse() {
            // Zeros where the sparse values do not say otherwise.
            Some(_) => Ok(()),
            None => bail!("{what} has no buffer view"),
        };
    };
    let elem = a.size();
    let stride = view.stride().unwrap_or(elem);
    if stride < elem || stride % a.data_type().size() != 0 {
        bail!(
            "{what}: buffer view {} stride {stride} for {elem}-byte elements",
            view.index()
        );
    }
    let need = match a.count() {
        0 => 0,
        n => a.offset() as u128 + stride as u128 * (n as u128 - 1) + elem as u128,
    };
    if need > view.length() as u128 {
        bail!(
            "{what}: {} elements need {need} bytes of buffer view {}, which has {}",
            a.count(),
            view.index(),
            view.length()
        );
    }
    if view.offset() as u128 + view.length() as u128 > view.buffer().length() as u128 {
        bail!(
            "buffer view {} ends past buffer {}'s {} bytes",
            view.index(),
            view.buffer().index(),
            view.buffer().length()
        );
    }
    Ok(())
}

/// A sparse accessor's substitutions lie inside their views and name elements it has.
fn check_sparse(
    a: &gltf::Accessor,
    sp: &gltf::accessor::sparse::Sparse,
    buffers: &[Buffer],
) -> Result<()> {
    let n = sp.count();
    if n > a.count() {
        bail!("{n} substitutions for {} elements", a.count());
    }
    let (iv, vv) = (sp.indices().view(), sp.values().view());
    let isize = sp.indices().index_type().size();
    let need_i = sp.indices().offset() as u128 + (n * isize) as u128;
    let need_v = sp.values().offset() as u128 + (n * a.size()) as u128;
    for (view, need) in [(&iv, need_i), (&vv, need_v)] {
        if need > view.length() as u128
            || view.offset() as u128 + view.length() as u128 > view.buffer().length() as u128
        {
            bail!(
                "buffer view {} is too short or lies outside its buffer",
                view.index()
            );
        }
    }
    if sparse_indices(sp, buffers, a.count()).is_none() {
        bail!("an index is past the accessor's {} elements", a.count());
    }
    Ok(())
}

/// A sparse accessor's substituted element numbers, or None if one is out of range.
fn sparse_indices(
    sp: &gltf::accessor::sparse::Sparse,
    buffers: &[Buffer],
    count: usize,
) -> Option<Vec<usize>> {
    use gltf::accessor::sparse::IndexType;
    let ind = sp.indices();
    let view = ind.view();
    let data = buffers.get(view.buffer().index())?;
    let start = view.offset() + ind.offset();
    let size = ind.index_type().size();
    (0..sp.count())
        .map(|k| {
            let b = data.get(start + k * size..start + (k + 1) * size)?;
            let i = match ind.index_type() {
                IndexType::U8 => b[0] as usize,
                IndexType::U16 => u16::from_le_bytes([b[0], b[1]]) as usize,
                IndexType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize,
            };
            (i < count).then_some(i)
        })
        .collect()
}

/// A checked accessor's N-component elements (`check_accessor`) as floats: F32 as stored,
/// integers as their values or, normalized, mapped to [−1, 1] or [0, 1] (glTF 3.11: c / 127
/// clamped at −1 for signed bytes, c / 255 for unsigned, and the same for 16 bits).
pub(super) fn read_floats<const N: usize>(
    a: &gltf::Accessor,
    buffers: &[Buffer],
) -> Option<Vec<[f32; N]>> {
    use gltf::accessor::DataType;
    let size = a.data_type().size();
    let norm = a.normalized();
    let value = |b: &[u8]| -> f32 {
        match a.data_type() {
            DataType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            DataType::I8 if norm => (b[0] as i8 as f32 / 127.0).max(-1.0),
            DataType::I8 => b[0] as i8 as f32,
            DataType::U8 if norm => b[0] as f32 / 255.0,
            DataType::U8 => b[0] as f32,
            DataType::I16 if norm => (i16::from_le_bytes([b[0], b[1]]) as f32 / 32767.0).max(-1.0),
            DataType::I16 => i16::from_le_bytes([b[0], b[1]]) as f32,
            DataType::U16 if norm => u16::from_le_bytes([b[0], b[1]]) as f32 / 65535.0,
            DataType::U16 => u16::from_le_bytes([b[0], b[1]]) as f32,
            DataType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
        }
    };
    let element = |data: &[u8], at: usize| -> Option<[f32; N]> {
        let e = data.get(at..at + N * size)?;
        Some(std::array::from_fn(|k| value(&e[k * size..])))
    };
    let mut out: Vec<[f32; N]> = match a.view() {
        Some(view) => {
            let data = buffers.get(view.buffer().index())?;
            let stride = view.stride().unwrap_or(N * size);
            let start = view.offset() + a.offset();
            (0..a.count())
                .map(|i| element(data, start + i * stride))
                .collect::<Option<_>>()?
        }
        None => vec![[0.0; N]; a.count()],
    };
    // Sparse storage (glTF 3.6.2.3): the listed elements replaced.
    if let Some(sp) = a.sparse() {
        let values = sp.values();
        let data = buffers.get(values.view().buffer().index())?;
        let start = values.view().offset() + values.offset();
        for (k, i) in sparse_indices(&sp, buffers, a.count())?
            .into_iter()
            .enumerate()
        {
            out[i] = element(data, start + k * N * size)?;
        }
    }
    Some(out)
}

/// A checked primitive's vertices from its accessors (`check_primitive`): positions,
/// normals and texture-coordinate sets `uv_sets`, and its indices; None without positions.
/// A `COLOR_0` accessor's colours as RGBA (alpha 1 for VEC3), None for another type.
fn colours(a: &gltf::Accessor, buffers: &[Buffer]) -> Option<Vec<[f32; 4]>> {
    match a.dimensions() {
        gltf::accessor::Dimensions::Vec4 => read_floats::<4>(a, buffers),
        gltf::accessor::Dimensions::Vec3 => Some(
            read_floats::<3>(a, buffers)?
                .into_iter()
                .map(|[r, g, b]| [r, g, b, 1.0])
                .collect(),
        ),
        _ => None,
    }
}

pub(super) fn accessor_vertices(
    prim: &gltf::Primitive,
    buffers: &[Buffer],
    uv_sets: [Option<u32>; 2],
) -> Option<Vertices> {
    let attribute = |s: gltf::Semantic| prim.get(&s).and_then(|a| read_floats::<3>(&a, buffers));
    let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d[..]));
    Some(Vertices {
        pos: attribute(gltf::Semantic::Positions)?,
        nrm: attribute(gltf::Semantic::Normals),
        uv: uv_sets.map(|set| {
            set.and_then(|s| prim.get(&gltf::Semantic::TexCoords(s)))
                .and_then(|a| read_floats::<2>(&a, buffers))
        }),
        colour: prim
            .get(&gltf::Semantic::Colors(0))
            .and_then(|a| colours(&a, buffers)),
        idx: reader.read_indices().map(|i| i.into_u32().collect()),
    })
}
