//! KHR_draco_mesh_compression: a primitive whose triangles and attributes are a Draco
//! bitstream in a buffer view, decoded by `draco-core` (a Rust port of Google's reference
//! decoder) one primitive at a time, so no more than one decoded primitive is held.
//!
//! The extension names the bitstream's buffer view and, per glTF attribute, the Draco
//! attribute's unique id; the decoded points are the vertices and the faces the triangles,
//! in place of the primitive's accessors (which keep only their count and type).

use super::buffer::Buffer;
use super::files::view_bytes;
use anyhow::{anyhow, bail, Result};
use draco_core::decoder_buffer::DecoderBuffer;
use draco_core::draco_types::DataType;
use draco_core::geometry_attribute::PointAttribute;
use draco_core::mesh::Mesh;
use draco_core::mesh_decoder::MeshDecoder;

pub(super) const DRACO: &str = "KHR_draco_mesh_compression";

/// A primitive's vertices and triangle list, read from its accessors or its Draco data.
pub(super) struct Vertices {
    pub pos: Vec<[f32; 3]>,
    pub nrm: Option<Vec<[f32; 3]>>,
    /// The texture-coordinate sets the material reads as its two streams, where it has them.
    pub uv: [Option<Vec<[f32; 2]>>; 2],
    /// `COLOR_0` as RGBA (alpha 1 for an RGB accessor).
    pub colour: Option<Vec<[f32; 4]>>,
    /// Indices into the vertices (None: the vertices in order).
    pub idx: Option<Vec<u32>>,
}

/// The Draco attribute id the extension gives glTF attribute `name`, if any.
fn attribute_id(ext: &serde_json::Value, name: &str) -> Result<Option<u32>> {
    match ext.get("attributes").and_then(|a| a.get(name)) {
        None => Ok(None),
        Some(v) => v
            .as_u64()
            .and_then(|v| u32::try_from(v).ok())
            .map(Some)
            .ok_or_else(|| anyhow!("its {DRACO} attribute {name} is {v}, not an id")),
    }
}

/// An attribute's values, `N` components a point; normalized integers mapped to [0, 1] or
/// [−1, 1] as glTF maps them.
fn values<const N: usize>(a: &PointAttribute, points: usize) -> Vec<[f32; N]> {
    let scale = match (a.normalized(), a.data_type()) {
        (true, DataType::Int8) => 1.0 / 127.0,
        (true, DataType::Uint8) => 1.0 / 255.0,
        (true, DataType::Int16) => 1.0 / 32767.0,
        (true, DataType::Uint16) => 1.0 / 65535.0,
        _ => 1.0,
    };
    a.read_f32s(points, N)
        .chunks_exact(N)
        .map(|c| {
            std::array::from_fn(|k| match a.normalized() {
                true => (c[k] * scale).max(-1.0),
                false => c[k],
            })
        })
        .collect()
}

/// The decoded vertices of a primitive that carries the extension (None if it does not):
/// positions, normals, texture-coordinate sets `uv_sets` and vertex colours.
pub(super) fn decode(
    prim: &gltf::Primitive,
    doc: &gltf::Document,
    buffers: &[Buffer],
    uv_sets: [Option<u32>; 2],
) -> Result<Option<Vertices>> {
    let Some(ext) = prim.extension_value(DRACO) else {
        return Ok(None);
    };
    let view = ext
        .get("bufferView")
        .and_then(|v| v.as_u64())
        .ok_or_else(|| anyhow!("its {DRACO} extension names no buffer view"))?;
    let view = doc.views().nth(view as usize).ok_or_else(|| {
        anyhow!("its {DRACO} extension names buffer view {view}, which does not exist")
    })?;
    let bytes = view_bytes(&view, buffers).ok_or_else(|| {
        anyhow!(
            "{DRACO} buffer view {} lies outside its buffer",
            view.index()
        )
    })?;
    let mut mesh = Mesh::new();
    MeshDecoder::new()
        .decode(&mut DecoderBuffer::new(bytes), &mut mesh)
        .map_err(|e| {
            anyhow!(
                "its {DRACO} data (buffer view {}) does not decode: {e:?}",
                view.index()
            )
        })?;
    let points = mesh.num_points();
    let get = |name: &str| -> Result<Option<&PointAttribute>> {
        match attribute_id(ext, name)? {
            None => Ok(None),
            Some(id) => mesh
                .attribute_by_unique_id(id)
                .map(Some)
                .ok_or_else(|| anyhow!("its {DRACO} data has no attribute {id} for {name}")),
        }
    };
    let Some(pos) = get("POSITION")? else {
        bail!("its {DRACO} extension gives no POSITION");
    };
    let set = |set: Option<u32>| match set {
        Some(s) => Ok(get(&format!("TEXCOORD_{s}"))?.map(|a| values::<2>(a, points))),
        None => Ok::<_, anyhow::Error>(None),
    };
    let uv = [set(uv_sets[0])?, set(uv_sets[1])?];
    let colour = match get("COLOR_0")? {
        Some(a) if a.num_components() == 4 => Some(values::<4>(a, points)),
        Some(a) => Some(
            values::<3>(a, points)
                .into_iter()
                .map(|[r, g, b]| [r, g, b, 1.0])
                .collect(),
        ),
        None => None,
    };
    let idx = mesh.faces().iter().flat_map(|f| f.map(|p| p.0)).collect();
    Ok(Some(Vertices {
        pos: values::<3>(pos, points),
        nrm: get("NORMAL")?.map(|a| values::<3>(a, points)),
        uv,
        colour,
        idx: Some(idx),
    }))
}
