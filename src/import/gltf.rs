//! glTF 2.0 (.gltf/.glb): mesh primitives under the default scene with node transforms
//! applied, meshes placed more than once stored once with their instances (unless the sink
//! flattens), perspective cameras, metallic-roughness materials with the
//! KHR extensions Canopy models, and KHR_lights_punctual.

use super::{make_tri, SceneDesc, TextureSource, TriangleSink};
use anyhow::{anyhow, bail, Context, Result};
use canopy_format::{name_bytes, CameraRecord, LightRecord, MaterialRecord, TextureRecord};
use glam::{Mat3, Mat4, Vec3};
use gltf::mesh::Mode;
use std::path::Path;

/// Largest external buffer or `.gltf` JSON read.
const MAX_SIDE_FILE: u64 = 16 << 30;

pub fn import(path: &Path, scene: &mut SceneDesc, sink: &mut dyn TriangleSink) -> Result<u64> {
    let (doc, buffers) = load(path)?;
    let (width, height) = render_size(&doc);
    let base = scene.materials.len() as u32;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut uv_maps = Vec::new();
    for m in doc.materials() {
        let named = |e: anyhow::Error| {
            anyhow!(
                "{}: material '{}': {e}",
                path.display(),
                m.name().unwrap_or("?")
            )
        };
        let (rec, uv) = material(&m, scene, &buffers, dir).map_err(named)?;
        if rec.flags & MaterialRecord::TEXTURED != 0 {
            scene.textured = true;
        }
        scene.add_material(rec)?;
        uv_maps.push(uv);
    }
    let mut default_mat = None;
    let gscene = doc
        .default_scene()
        .or_else(|| doc.scenes().next())
        .ok_or_else(|| anyhow!("{}: no scene", path.display()))?;
    check_forest(&doc).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let shared = shared_meshes(&doc, &buffers, scene, base, sink.shares_meshes());
    let mut prototypes: Vec<Option<(u32, u64)>> = vec![None; doc.meshes().len()];
    let mut count = 0u64;
    // Depth-first pre-order, roots and children in the order the file lists them: cameras,
    // lights and triangles keep the file's order (FORMAT.md states it).
    let mut stack: Vec<(gltf::Node, Mat4)> = gscene.nodes().map(|n| (n, Mat4::IDENTITY)).collect();
    stack.reverse();
    let mut seen = vec![false; doc.nodes().len()];
    while let Some((node, parent)) = stack.pop() {
        if std::mem::replace(&mut seen[node.index()], true) {
            bail!(
                "{}: node {} is reached twice from the scene (glTF nodes form trees)",
                path.display(),
                node.index()
            );
        }
        let world = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
        if !world.is_finite() {
            bail!(
                "{}: node '{}' has a non-finite transform",
                path.display(),
                node.name().unwrap_or("?")
            );
        }
        let first = stack.len();
        stack.extend(node.children().map(|child| (child, world)));
        stack[first..].reverse();
        if let Some(cam) = node.camera() {
            if let Some(rec) = camera(&cam, &node, world, width, height) {
                scene.cameras.push(rec);
            }
        }
        if let Some(light) = node.light() {
            scene.lights.push(punctual(&light, world));
        }
        let Some(mesh) = node.mesh() else { continue };
        let named = |e: anyhow::Error| {
            anyhow!(
                "{}: node '{}': {e}",
                path.display(),
                node.name().unwrap_or("?")
            )
        };
        let instances = gpu_instances(&doc, &node, &buffers).map_err(named)?;
        if instances.iter().any(|i| !(world * *i).is_finite()) {
            bail!(
                "{}: node '{}' has an instance with a non-finite transform",
                path.display(),
                node.name().unwrap_or("?")
            );
        }
        let mut m = MeshCtx {
            path,
            mesh: &mesh,
            buffers: &buffers,
            uv_maps: &uv_maps,
            base,
            default_mat: &mut default_mat,
            scene,
            sink,
        };
        if !shared[mesh.index()] {
            for instance in instances {
                count += m.push(world * instance)?;
            }
            continue;
        }
        let (proto, tris) = match prototypes[mesh.index()] {
            Some(p) => p,
            None => {
                m.sink.begin_prototype()?;
                m.push(Mat4::IDENTITY)?;
                *prototypes[mesh.index()].insert(m.sink.end_prototype()?)
            }
        };
        if tris == 0 {
            continue;
        }
        for instance in instances {
            let c = (world * instance).to_cols_array();
            let to_world = std::array::from_fn(|i| c[i / 3 * 4 + i % 3]);
            sink.instance(proto, to_world)?;
            count += tris;
        }
    }
    Ok(count)
}

/// Meshes to store once as prototypes: placed more than once (by several nodes or
/// EXT_mesh_gpu_instancing) and emitting no light (the light sampler works on world-space
/// emitters, so emissive meshes are flattened). None when the sink flattens.
fn shared_meshes(
    doc: &gltf::Document,
    buffers: &[Vec<u8>],
    scene: &SceneDesc,
    base: u32,
    sharing: bool,
) -> Vec<bool> {
    let mut uses = vec![0usize; doc.meshes().len()];
    if sharing {
        for node in doc.nodes() {
            if let Some(m) = node.mesh() {
                // A bad instancing extension is reported by the walk, naming the node.
                uses[m.index()] += gpu_instances(doc, &node, buffers).map_or(1, |i| i.len());
            }
        }
    }
    doc.meshes()
        .map(|mesh| {
            uses[mesh.index()] >= 2
                && mesh.primitives().all(|p| {
                    p.material().index().is_none_or(|i| {
                        scene.materials[base as usize + i]
                            .emission
                            .iter()
                            .all(|&e| e <= 0.0)
                    })
                })
        })
        .collect()
}

/// One mesh's primitives pushed under a transform.
struct MeshCtx<'a> {
    path: &'a Path,
    mesh: &'a gltf::Mesh<'a>,
    buffers: &'a [Vec<u8>],
    /// The file's first material in the scene's table.
    /// Per glTF material, how its texture coordinates are read (None: untextured).
    uv_maps: &'a [Option<UvMap>],
    base: u32,
    default_mat: &'a mut Option<u32>,
    scene: &'a mut SceneDesc,
    sink: &'a mut dyn TriangleSink,
}

impl MeshCtx<'_> {
    /// Pushes every triangle of the mesh transformed by `world` (mirroring transforms
    /// reverse the winding); returns how many.
    fn push(&mut self, world: Mat4) -> Result<u64> {
        let (path, mesh) = (self.path, self.mesh);
        let normal_m = Mat3::from_mat4(world).inverse().transpose();
        let flip = world.determinant() < 0.0;
        let mut count = 0;
        for (pi, prim) in mesh.primitives().enumerate() {
            let what = |t: usize| {
                format!(
                    "{}: mesh '{}' primitive {pi} triangle {t}",
                    path.display(),
                    mesh.name().unwrap_or("?")
                )
            };
            let mat = match (prim.material().index(), *self.default_mat) {
                (Some(i), _) => self.base + i as u32,
                (None, Some(m)) => m,
                (None, None) => {
                    let m = self
                        .scene
                        .add_material(super::default_material("default"))?;
                    *self.default_mat.insert(m)
                }
            };
            check_primitive(&prim).map_err(|e| anyhow!("{}: {e}", what(0)))?;
            let buffers = self.buffers;
            let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d[..]));
            let Some(pos) = reader.read_positions() else {
                continue;
            };
            let pos: Vec<Vec3> = pos.map(|p| world.transform_point3(Vec3::from(p))).collect();
            let nrm: Option<Vec<Vec3>> = reader
                .read_normals()
                .map(|n| {
                    n.map(|n| (normal_m * Vec3::from(n)).normalize_or_zero())
                        .collect::<Vec<_>>()
                })
                .filter(|n| n.len() == pos.len());
            if nrm.is_some() {
                self.scene.has_normals = true;
            }
            let uv_map = prim.material().index().and_then(|i| self.uv_maps[i]);
            let uvs: Option<Vec<[f32; 2]>> = match uv_map {
                Some(map) => reader
                    .read_tex_coords(map.set)
                    .map(|t| t.into_f32().map(|uv| map.apply(uv)).collect::<Vec<_>>())
                    .filter(|t| t.len() == pos.len()),
                None => None,
            };
            if uvs.is_some() {
                self.scene.has_uvs = true;
            }
            let idx: Vec<u32> = match reader.read_indices() {
                Some(i) => i.into_u32().collect(),
                None => (0..pos.len() as u32).collect(),
            };
            for (t, mut tri) in triangles(prim.mode(), &idx).enumerate() {
                if flip {
                    tri.swap(1, 2);
                }
                if let Some(&bad) = tri.iter().find(|&&i| i as usize >= pos.len()) {
                    bail!(
                        "{}: index {bad} out of range ({} vertices)",
                        what(t),
                        pos.len()
                    );
                }
                let p = tri.map(|i| pos[i as usize].to_array());
                let n = nrm.as_ref().map(|n| tri.map(|i| n[i as usize].to_array()));
                let mut st = make_tri(p, n, mat, &|| what(t))?;
                if let Some(uv) = &uvs {
                    st.uv = tri.map(|i| uv[i as usize]);
                    if st.uv.iter().flatten().any(|x| !x.is_finite()) {
                        bail!("{}: non-finite texture coordinate {:?}", what(t), st.uv);
                    }
                }
                self.sink.push(st)?;
                count += 1;
            }
        }
        Ok(count)
    }
}

/// glTF nodes form a forest: no node is the child of two nodes or its own ancestor (the
/// spec's rule; a DAG or a cycle would otherwise multiply or repeat instances without end).
fn check_forest(doc: &gltf::Document) -> Result<()> {
    let mut parent = vec![None; doc.nodes().len()];
    for n in doc.nodes() {
        for c in n.children() {
            if let Some(p) = parent[c.index()].replace(n.index()) {
                bail!(
                    "node {} is a child of node {p} and again of node {} (glTF nodes form trees)",
                    c.index(),
                    n.index()
                );
            }
        }
    }
    // Walk up from every node; a node on the current walk met again is a cycle. Nodes whose
    // ancestry is known good end later walks, so the whole check is linear.
    let mut state = vec![0u8; parent.len()]; // 0 unknown, 1 on the current walk, 2 good
    let mut walk = Vec::new();
    for start in 0..parent.len() {
        let mut at = Some(start);
        while let Some(i) = at.filter(|&i| state[i] != 2) {
            if state[i] == 1 {
                bail!("node {i} is its own ancestor");
            }
            state[i] = 1;
            walk.push(i);
            at = parent[i];
        }
        for i in walk.drain(..) {
            state[i] = 2;
        }
    }
    Ok(())
}

/// Parses the document (the gltf crate's validation runs after our own index checks, as
/// one of its hooks indexes accessors unchecked) and loads its buffers, each checked
/// against its declared length. Images are never read: textures are not stored.
fn load(path: &Path) -> Result<(gltf::Document, Vec<Vec<u8>>)> {
    let bytes = super::read_regular(path, u64::MAX, "glTF file")?;
    let bad = |e: &dyn std::fmt::Display| anyhow!("{}: not a valid glTF file: {e}", path.display());
    let g = gltf::Gltf::from_slice_without_validation(&bytes).map_err(|e| bad(&e))?;
    let blob = g.blob;
    let json = g.document.into_json();
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
    check_images(&json).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let doc = gltf::Document::from_json(json).map_err(|e| bad(&e))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let buffers = doc
        .buffers()
        .map(|b| load_buffer(&b, blob.as_deref(), dir))
        .collect::<Result<Vec<_>>>()
        .with_context(|| path.display().to_string())?;
    Ok((doc, buffers))
}

/// Every texture's image and sampler exist, and every image names a buffer view in range
/// with its MIME type, or a URI (the gltf crate's accessors unwrap these).
fn check_images(json: &gltf::json::Root) -> Result<()> {
    for (i, t) in json.textures.iter().enumerate() {
        if t.source.value() >= json.images.len() {
            bail!(
                "texture {i} names image {} of {}",
                t.source.value(),
                json.images.len()
            );
        }
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

/// The bytes of a base64 `data:` URI.
fn data_uri(uri: &str) -> Result<Vec<u8>> {
    use base64::Engine;
    let (_, payload) = uri
        .split_once(";base64,")
        .ok_or_else(|| anyhow!("a data URI that is not base64"))?;
    base64::engine::general_purpose::STANDARD
        .decode(payload)
        .map_err(|e| anyhow!("bad base64 data: {e}"))
}

/// The file name a URI gives, percent-decoded; refused unless relative (no scheme).
fn relative_file(uri: &str) -> Result<String> {
    let name = urlencoding::decode(uri).map_err(|_| anyhow!("URI {uri:?} is not UTF-8"))?;
    if name.contains(':') {
        bail!("URI {uri:?} is not a relative file name");
    }
    Ok(name.into_owned())
}

/// One buffer's bytes: the GLB BIN chunk (its length the declared one, padded by at most 3
/// bytes, as the GLB spec writes it), a base64 data URI, or a regular file beside the glTF.
fn load_buffer(b: &gltf::Buffer, blob: Option<&[u8]>, dir: &Path) -> Result<Vec<u8>> {
    let want = b.length();
    let i = b.index();
    let mut data = match b.source() {
        gltf::buffer::Source::Bin => {
            let bin = blob.ok_or_else(|| anyhow!("buffer {i} refers to a missing BIN chunk"))?;
            if bin.len() < want || bin.len() > want + 3 {
                bail!(
                    "buffer {i} declares {want} bytes, the BIN chunk holds {}",
                    bin.len()
                );
            }
            bin.to_vec()
        }
        gltf::buffer::Source::Uri(uri) if uri.starts_with("data:") => {
            data_uri(uri).map_err(|e| anyhow!("buffer {i}: {e}"))?
        }
        gltf::buffer::Source::Uri(uri) => {
            let name = relative_file(uri).map_err(|e| anyhow!("buffer {i}: {e}"))?;
            super::read_regular(&dir.join(&name), MAX_SIDE_FILE, "glTF buffer")?
        }
    };
    if data.len() < want {
        bail!("buffer {i} declares {want} bytes but holds {}", data.len());
    }
    data.truncate(want);
    Ok(data)
}

/// A node's EXT_mesh_gpu_instancing transforms (translation, rotation, scale per instance,
/// in the node's space), or the identity alone.
fn gpu_instances(
    doc: &gltf::Document,
    node: &gltf::Node,
    buffers: &[Vec<u8>],
) -> Result<Vec<Mat4>> {
    use gltf::accessor::{DataType, Dimensions, Iter};
    let Some(ext) = node.extension_value("EXT_mesh_gpu_instancing") else {
        return Ok(vec![Mat4::IDENTITY]);
    };
    let accessor = |name: &str, dims| -> Result<Option<gltf::Accessor>> {
        let Some(v) = ext["attributes"].get(name) else {
            return Ok(None);
        };
        let a = v
            .as_u64()
            .and_then(|i| doc.accessors().nth(i as usize))
            .ok_or_else(|| anyhow!("EXT_mesh_gpu_instancing {name}: {v} is not an accessor"))?;
        check_accessor(
            &a,
            &format!("{name} accessor {}", a.index()),
            &[DataType::F32],
            dims,
        )?;
        Ok(Some(a))
    };
    let data = |b: gltf::Buffer| buffers.get(b.index()).map(|d| &d[..]);
    let read3 = |a: Option<gltf::Accessor>| {
        a.and_then(|a| Iter::<[f32; 3]>::new(a, data))
            .map(|it| it.map(Vec3::from).collect::<Vec<_>>())
    };
    let t = read3(accessor("TRANSLATION", Dimensions::Vec3)?);
    let s = read3(accessor("SCALE", Dimensions::Vec3)?);
    let r: Option<Vec<glam::Quat>> = accessor("ROTATION", Dimensions::Vec4)?
        .and_then(|a| Iter::<[f32; 4]>::new(a, data))
        .map(|it| it.map(|q| glam::Quat::from_array(q).normalize()).collect());
    let counts: Vec<usize> = [
        t.as_ref().map(Vec::len),
        r.as_ref().map(Vec::len),
        s.as_ref().map(Vec::len),
    ]
    .into_iter()
    .flatten()
    .collect();
    let Some(&n) = counts.first() else {
        bail!("EXT_mesh_gpu_instancing names no TRANSLATION, ROTATION or SCALE accessor");
    };
    if counts.iter().any(|&c| c != n) {
        bail!("EXT_mesh_gpu_instancing accessors of {counts:?} elements (the spec requires one count)");
    }
    Ok((0..n)
        .map(|i| {
            Mat4::from_scale_rotation_translation(
                s.as_ref().map_or(Vec3::ONE, |s| s[i]),
                r.as_ref().map_or(glam::Quat::IDENTITY, |r| r[i]),
                t.as_ref().map_or(Vec3::ZERO, |t| t[i]),
            )
        })
        .collect())
}

/// The accessors a primitive's triangles are read from, checked before the gltf crate reads
/// them (`check_accessor`).
fn check_primitive(prim: &gltf::Primitive) -> Result<()> {
    use gltf::accessor::{DataType, Dimensions};
    use gltf::Semantic;
    let mut wanted: Vec<(gltf::Accessor, &str, &[DataType], Dimensions)> = Vec::new();
    for (sem, a) in prim.attributes() {
        match sem {
            Semantic::Positions => wanted.push((a, "POSITION", &[DataType::F32], Dimensions::Vec3)),
            Semantic::Normals => wanted.push((a, "NORMAL", &[DataType::F32], Dimensions::Vec3)),
            _ => {}
        }
    }
    if let Some(a) = prim.indices() {
        let ints: &[DataType] = &[DataType::U8, DataType::U16, DataType::U32];
        wanted.push((a, "indices", ints, Dimensions::Scalar));
    }
    for (a, name, types, dims) in wanted {
        check_accessor(&a, &format!("{name} accessor {}", a.index()), types, dims)?;
    }
    Ok(())
}

/// An accessor checked before the gltf crate reads it: a type the spec allows, no sparse
/// storage, every element inside its buffer view and the view inside its buffer.
fn check_accessor(
    a: &gltf::Accessor,
    what: &str,
    types: &[gltf::accessor::DataType],
    dims: gltf::accessor::Dimensions,
) -> Result<()> {
    if !types.contains(&a.data_type()) || a.dimensions() != dims || a.normalized() {
        bail!(
            "{what} is {:?} {:?}{}, the spec requires {dims:?} of {types:?}",
            a.dimensions(),
            a.data_type(),
            if a.normalized() { " normalized" } else { "" }
        );
    }
    if a.sparse().is_some() {
        bail!("{what} is sparse, which Canopy does not read");
    }
    let Some(view) = a.view() else {
        bail!("{what} has no buffer view");
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

/// Triangle index triples for a primitive's topology; points and lines give none.
fn triangles(mode: Mode, idx: &[u32]) -> Box<dyn Iterator<Item = [u32; 3]> + '_> {
    match mode {
        Mode::Triangles => Box::new(idx.chunks_exact(3).map(|c| [c[0], c[1], c[2]])),
        Mode::TriangleStrip => Box::new((2..idx.len()).map(move |i| {
            if i % 2 == 0 {
                [idx[i - 2], idx[i - 1], idx[i]]
            } else {
                [idx[i - 1], idx[i - 2], idx[i]]
            }
        })),
        Mode::TriangleFan => Box::new((2..idx.len()).map(move |i| [idx[0], idx[i - 1], idx[i]])),
        _ => Box::new(std::iter::empty()),
    }
}

/// The render resolution the bundled scenes carry in top-level `extras.render`.
fn render_size(doc: &gltf::Document) -> (u32, u32) {
    let extras = doc
        .as_json()
        .extras
        .as_ref()
        .and_then(|e| serde_json::from_str::<serde_json::Value>(e.get()).ok());
    let get = |k: &str| {
        extras
            .as_ref()
            .and_then(|e| e["render"][k].as_u64())
            .map(|v| v as u32)
            .unwrap_or(0)
    };
    (get("width"), get("height"))
}

/// How a material's texture coordinates are read: the set, then KHR_texture_transform's
/// matrix (translation · rotation · scale, rows of a 2×3 affine map).
#[derive(Clone, Copy, Debug, PartialEq)]
struct UvMap {
    set: u32,
    m: [[f32; 3]; 2],
}

impl UvMap {
    fn of(info: &gltf::texture::Info) -> UvMap {
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
    fn of_normal(n: &gltf::material::NormalTexture) -> Result<UvMap> {
        use gltf::json::extensions::texture::TextureTransform;
        Ok(match n.extension_value("KHR_texture_transform") {
            Some(v) => {
                let t: TextureTransform = serde_json::from_value(v.clone())
                    .context("normalTexture's KHR_texture_transform")?;
                UvMap::new(
                    t.tex_coord.unwrap_or(n.tex_coord()),
                    t.offset.0,
                    t.rotation.0,
                    t.scale.0,
                )
            }
            None => UvMap::new(n.tex_coord(), [0.0; 2], 0.0, [1.0; 2]),
        })
    }

    /// KHR_texture_transform: translation · rotation · scale.
    fn new(set: u32, [ox, oy]: [f32; 2], r: f32, [sx, sy]: [f32; 2]) -> UvMap {
        let (s, c) = r.sin_cos();
        UvMap {
            set,
            m: [[c * sx, s * sy, ox], [-s * sx, c * sy, oy]],
        }
    }

    fn apply(&self, [u, v]: [f32; 2]) -> [f32; 2] {
        self.m.map(|r| r[0] * u + r[1] * v + r[2])
    }
}

/// The material record, its textures added to `scene`, and how its texture coordinates are
/// read. All textures of a material share one coordinate set and transform (the archive
/// stores one set per vertex); a material that mixes them is refused.
fn material(
    m: &gltf::Material,
    scene: &mut SceneDesc,
    buffers: &[Vec<u8>],
    dir: &Path,
) -> Result<(MaterialRecord, Option<UvMap>)> {
    let pbr = m.pbr_metallic_roughness();
    let strength = m.emissive_strength().unwrap_or(1.0);
    let spec = m.specular();
    let normal = m.normal_texture();
    let textured = pbr.base_color_texture().is_some()
        || pbr.metallic_roughness_texture().is_some()
        || m.emissive_texture().is_some()
        || normal.is_some();
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
    let mut textures = [MaterialRecord::NO_TEXTURE; 4];
    let mut uv: Option<UvMap> = None;
    fn info(i: gltf::texture::Info<'_>) -> (Result<UvMap>, gltf::Texture<'_>) {
        (Ok(UvMap::of(&i)), i.texture())
    }
    let slots = [
        (
            MaterialRecord::BASE_COLOR,
            pbr.base_color_texture().map(info),
            true,
        ),
        (
            MaterialRecord::METALLIC_ROUGHNESS,
            pbr.metallic_roughness_texture().map(info),
            false,
        ),
        (
            MaterialRecord::EMISSIVE,
            m.emissive_texture().map(info),
            true,
        ),
        (
            MaterialRecord::NORMAL,
            normal.as_ref().map(|n| (UvMap::of_normal(n), n.texture())),
            false,
        ),
    ];
    for (slot, found, srgb) in slots {
        let Some((map, texture)) = found else {
            continue;
        };
        let map = map?;
        if uv.is_some_and(|u| u != map) {
            bail!("its textures use different texture coordinates or transforms (Canopy stores one set per vertex)");
        }
        uv = Some(map);
        textures[slot] = scene.add_texture(texture_source(&texture, srgb, buffers, dir)?)?;
    }
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
        textures,
        alpha_cutoff: m.alpha_cutoff().unwrap_or(0.5),
        normal_scale: normal.as_ref().map_or(0.0, |n| n.scale()),
    };
    Ok((rec, uv))
}

/// Where a glTF texture's image is: a buffer view, a data URI or a file beside the glTF.
fn texture_source(
    t: &gltf::Texture,
    srgb: bool,
    buffers: &[Vec<u8>],
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
            let data = buffers
                .get(view.buffer().index())
                .and_then(|b| b.get(view.offset()..view.offset().checked_add(view.length())?))
                .ok_or_else(|| {
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

fn camera(
    cam: &gltf::Camera,
    node: &gltf::Node,
    world: Mat4,
    width: u32,
    height: u32,
) -> Option<CameraRecord> {
    let gltf::camera::Projection::Perspective(p) = cam.projection() else {
        return None;
    };
    let c = world.to_cols_array();
    let mut to_world = [0.0f32; 12];
    for col in 0..4 {
        to_world[col * 3..col * 3 + 3].copy_from_slice(&c[col * 4..col * 4 + 3]);
    }
    let name = node
        .name()
        .or(cam.name())
        .map(str::to_string)
        .unwrap_or_else(|| format!("camera{}", cam.index()));
    Some(CameraRecord {
        name: name_bytes(&name),
        to_world,
        yfov: p.yfov(),
        aspect: p.aspect_ratio().unwrap_or(0.0),
        znear: p.znear(),
        zfar: p.zfar().unwrap_or(0.0),
        width,
        height,
        reserved: [0; 8],
    })
}

fn punctual(l: &gltf::khr_lights_punctual::Light, world: Mat4) -> LightRecord {
    use gltf::khr_lights_punctual::Kind;
    let (kind, inner, outer) = match l.kind() {
        Kind::Point => (LightRecord::POINT, 0.0, 0.0),
        Kind::Spot {
            inner_cone_angle,
            outer_cone_angle,
        } => (LightRecord::SPOT, inner_cone_angle, outer_cone_angle),
        Kind::Directional => (LightRecord::DIRECTIONAL, 0.0, 0.0),
    };
    LightRecord {
        name: name_bytes(l.name().unwrap_or("")),
        kind,
        color: l.color(),
        intensity: l.intensity(),
        position: world.transform_point3(Vec3::ZERO).to_array(),
        direction: world
            .transform_vector3(Vec3::NEG_Z)
            .normalize_or_zero()
            .to_array(),
        range: l.range().unwrap_or(0.0),
        inner_cone: inner,
        outer_cone: outer,
        reserved: [0; 8],
    }
}
