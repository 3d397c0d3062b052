//! glTF 2.0 (.gltf/.glb): mesh primitives under the default scene with node transforms
//! applied, meshes placed more than once stored once with their instances (unless the sink
//! flattens), perspective cameras, metallic-roughness materials with the
//! KHR extensions Canopy models, and KHR_lights_punctual.

use super::{make_tri, unorm16, SceneDesc, TriangleSink};
use anyhow::{anyhow, bail, Result};
use buffer::Buffer;
use canopy_format::MaterialRecord;
use glam::{Mat3, Mat4, Vec3};
use gltf::accessor::Dimensions;
use gltf::mesh::Mode;
use std::path::Path;

mod buffer;
mod draco;
mod files;
mod layers;
mod material;
mod meshopt;
mod view;
use files::{accessor_vertices, check_accessor, check_primitive, load};
use material::{material, UvSets};
use view::{camera, punctual, render_size};

pub fn import(path: &Path, scene: &mut SceneDesc, sink: &mut dyn TriangleSink) -> Result<u64> {
    let (doc, buffers, unsourced) = load(path)?;
    name_unsupported(path, &doc, scene);
    let (width, height) = render_size(&doc);
    let base = scene.materials.len() as u32;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut uv_sets = Vec::new();
    for m in doc.materials() {
        let named = |e: anyhow::Error| {
            anyhow!(
                "{}: material '{}': {e}",
                path.display(),
                m.name().unwrap_or("?")
            )
        };
        let mut notes = Vec::new();
        let (rec, uv) =
            material(&m, (&doc, &unsourced), scene, &buffers, dir, &mut notes).map_err(named)?;
        for note in notes {
            let name = m.name().unwrap_or("?");
            scene.note(format!("{}: material '{name}': {note}", path.display()));
        }
        if rec.flags & MaterialRecord::TEXTURED != 0 {
            scene.textured = true;
        }
        scene.add_material(rec)?;
        uv_sets.push(uv);
    }
    let mut default_mat = None;
    let gscene = doc
        .default_scene()
        .or_else(|| doc.scenes().next())
        .ok_or_else(|| anyhow!("{}: no scene", path.display()))?;
    check_forest(&doc).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let shared = shared_meshes(&doc, scene, base, sink.shares_meshes());
    let mut prototypes: Vec<Option<(u32, u64)>> = vec![None; doc.meshes().len()];
    let mut count = 0u64;
    let mut released = buffer::Releaser::default();
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
            match camera(&cam, &node, world, width, height) {
                Some(rec) => scene.cameras.push(rec),
                None => scene.note(format!(
                    "{}: orthographic camera '{}' has a zero or non-finite magnification; it is not recorded (a render takes another camera, or frames the bounds)",
                    path.display(),
                    node.name().or(cam.name()).unwrap_or("?")
                )),
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
        // Each placement in world space, checked finite (an error stops the import).
        let placements = instances.iter().map(|i| {
            let m = world * i;
            match m.is_finite() {
                true => Ok(m),
                false => Err(named(anyhow!("an instance has a non-finite transform"))),
            }
        });
        let mut m = MeshCtx {
            path,
            doc: &doc,
            mesh: &mesh,
            buffers: &buffers,
            uv_sets: &uv_sets,
            base,
            default_mat: &mut default_mat,
            scene,
            sink,
        };
        if !shared[mesh.index()] {
            for placed in placements {
                let tris = m.push(placed?)?;
                count += tris;
                released.read(tris, &buffers);
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
        for placed in placements {
            let c = placed?.to_cols_array();
            let to_world = std::array::from_fn(|i| c[i / 3 * 4 + i % 3]);
            sink.instance(proto, to_world)?;
            count += tris;
            released.read(1, &buffers);
        }
    }
    Ok(count)
}

/// Meshes to store once as prototypes: placed more than once (by several nodes or
/// EXT_mesh_gpu_instancing) and emitting no light (the light sampler works on world-space
/// emitters, so emissive meshes are flattened). None when the sink flattens.
fn shared_meshes(doc: &gltf::Document, scene: &SceneDesc, base: u32, sharing: bool) -> Vec<bool> {
    let mut uses = vec![0usize; doc.meshes().len()];
    if sharing {
        for node in doc.nodes() {
            if let Some(m) = node.mesh() {
                uses[m.index()] += gpu_instance_count(doc, &node);
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
    doc: &'a gltf::Document,
    mesh: &'a gltf::Mesh<'a>,
    buffers: &'a [Buffer],
    /// The file's first material in the scene's table.
    /// Per glTF material, the texture-coordinate sets its textures read.
    uv_sets: &'a [UvSets],
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
            let uv_sets = match prim.material().index() {
                Some(i) => self.uv_sets[i],
                None => [None; 2],
            };
            let decoded = draco::decode(&prim, self.doc, self.buffers, uv_sets)
                .map_err(|e| anyhow!("{}: {e}", what(0)))?;
            let v = match decoded {
                Some(v) => v,
                None => {
                    check_primitive(&prim, self.buffers)
                        .map_err(|e| anyhow!("{}: {e}", what(0)))?;
                    let Some(v) = accessor_vertices(&prim, self.buffers, uv_sets) else {
                        continue;
                    };
                    v
                }
            };
            let pos: Vec<Vec3> = v
                .pos
                .iter()
                .map(|&p| world.transform_point3(Vec3::from(p)))
                .collect();
            let nrm: Option<Vec<Vec3>> = v
                .nrm
                .map(|n| {
                    n.iter()
                        .map(|&n| (normal_m * Vec3::from(n)).normalize_or_zero())
                        .collect::<Vec<_>>()
                })
                .filter(|n| n.len() == pos.len());
            if nrm.is_some() {
                self.scene.has_normals = true;
            }
            let [uvs, uvs2] = v.uv.map(|t| t.filter(|t| t.len() == pos.len()));
            self.scene.has_uvs |= uvs.is_some() || uvs2.is_some();
            self.scene.has_uvs2 |= uvs2.is_some();
            let colours: Option<Vec<[u16; 4]>> = v
                .colour
                .filter(|c| c.len() == pos.len())
                .map(|c| c.iter().map(|c| c.map(unorm16)).collect());
            if colours.is_some() {
                self.scene.has_colours = true;
            }
            let idx = v.idx.unwrap_or_else(|| (0..pos.len() as u32).collect());
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
                for (uv, out) in [(&uvs, &mut st.uv), (&uvs2, &mut st.uv2)] {
                    if let Some(uv) = uv {
                        *out = tri.map(|i| uv[i as usize]);
                        if out.iter().flatten().any(|x| !x.is_finite()) {
                            bail!("{}: non-finite texture coordinate {out:?}", what(t));
                        }
                    }
                }
                if let Some(c) = &colours {
                    st.colour = tri.map(|i| c[i as usize]);
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

/// A node's EXT_mesh_gpu_instancing placements: translation, rotation and scale columns
/// (each optional, checked), read from their buffers and made into matrices one at a time
/// as they are used, so that millions of instances are never held in memory.
struct GpuInstances<'a> {
    t: Option<gltf::Accessor<'a>>,
    r: Option<gltf::Accessor<'a>>,
    s: Option<gltf::Accessor<'a>>,
    buffers: &'a [Buffer],
    /// How many (1 without the extension: the identity).
    n: usize,
}

impl GpuInstances<'_> {
    /// The transforms in the node's space, in order.
    fn iter(&self) -> impl Iterator<Item = Mat4> + '_ {
        use gltf::accessor::Iter;
        let data = |b: gltf::Buffer| self.buffers.get(b.index()).map(|d| &d[..]);
        let column =
            |a: &Option<gltf::Accessor>| a.clone().and_then(|a| Iter::<[f32; 3]>::new(a, data));
        let mut t = column(&self.t);
        let mut s = column(&self.s);
        let mut r = self.r.clone().and_then(|a| Iter::<[f32; 4]>::new(a, data));
        (0..self.n).map(move |_| {
            let at = |c: &mut Option<Iter<'_, [f32; 3]>>, or| {
                c.as_mut().and_then(Iterator::next).map_or(or, Vec3::from)
            };
            let q = r.as_mut().and_then(Iterator::next);
            Mat4::from_scale_rotation_translation(
                at(&mut s, Vec3::ONE),
                q.map_or(glam::Quat::IDENTITY, |q| {
                    glam::Quat::from_array(q).normalize()
                }),
                at(&mut t, Vec3::ZERO),
            )
        })
    }
}

/// How many placements a node's EXT_mesh_gpu_instancing makes (1 without it), from its
/// first accessor's count alone: the columns are read once, by the walk, which reports a
/// bad extension naming the node (counted here as 1).
fn gpu_instance_count(doc: &gltf::Document, node: &gltf::Node) -> usize {
    let Some(ext) = node.extension_value("EXT_mesh_gpu_instancing") else {
        return 1;
    };
    ["TRANSLATION", "ROTATION", "SCALE"]
        .iter()
        .find_map(|name| {
            let i = ext["attributes"].get(name)?.as_u64()?;
            doc.accessors().nth(i as usize).map(|a| a.count())
        })
        .unwrap_or(1)
}

/// A node's EXT_mesh_gpu_instancing transforms (translation, rotation, scale per instance,
/// in the node's space), or the identity alone.
fn gpu_instances<'a>(
    doc: &'a gltf::Document,
    node: &gltf::Node,
    buffers: &'a [Buffer],
) -> Result<GpuInstances<'a>> {
    use gltf::accessor::{DataType, Dimensions};
    let Some(ext) = node.extension_value("EXT_mesh_gpu_instancing") else {
        return Ok(GpuInstances {
            t: None,
            r: None,
            s: None,
            buffers,
            n: 1,
        });
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
            buffers,
        )?;
        Ok(Some(a))
    };
    let t = accessor("TRANSLATION", Dimensions::Vec3)?;
    let s = accessor("SCALE", Dimensions::Vec3)?;
    let r = accessor("ROTATION", Dimensions::Vec4)?;
    let counts: Vec<usize> = [&t, &r, &s]
        .into_iter()
        .flatten()
        .map(gltf::Accessor::count)
        .collect();
    let Some(&n) = counts.first() else {
        bail!("EXT_mesh_gpu_instancing names no TRANSLATION, ROTATION or SCALE accessor");
    };
    if counts.iter().any(|&c| c != n) {
        bail!("EXT_mesh_gpu_instancing accessors of {counts:?} elements (the spec requires one count)");
    }
    Ok(GpuInstances {
        t,
        r,
        s,
        buffers,
        n,
    })
}

/// Notes what the file holds that Canopy does not render, naming where and what is done
/// instead: extensions it does not read (ignored; material extensions name their
/// materials), COLOR_0 of a type glTF does not allow (ignored), primitives of points and
/// lines (skipped), morph targets (the base shape is kept) and skins (the bind pose is kept).
fn name_unsupported(path: &Path, doc: &gltf::Document, scene: &mut SceneDesc) {
    for ext in doc.extensions_used().filter(|e| !files::READ.contains(e)) {
        let users: Vec<String> = doc
            .materials()
            .filter(|m| m.extension_value(ext).is_some())
            .map(|m| format!("'{}'", m.name().unwrap_or("?")))
            .collect();
        match users.is_empty() {
            true => scene.note(format!(
                "{}: uses {ext}, which Canopy does not read; it is ignored",
                path.display()
            )),
            false => scene.note(format!(
                "{}: materials {} use {ext}, which Canopy does not render; they are shaded as metallic-roughness without it",
                path.display(),
                users.join(", ")
            )),
        }
    }
    for mesh in doc.meshes() {
        let name = mesh.name().unwrap_or("?");
        for (pi, prim) in mesh.primitives().enumerate() {
            if let Some(a) = prim.get(&gltf::Semantic::Colors(0)) {
                let dims = a.dimensions();
                if !matches!(dims, Dimensions::Vec3 | Dimensions::Vec4) {
                    scene.note(format!(
                        "{}: mesh '{name}' primitive {pi} has COLOR_0 of type {dims:?} (glTF allows VEC3 and VEC4); its vertex colours are ignored",
                        path.display()
                    ));
                }
            }
            let mode = prim.mode();
            if !matches!(
                mode,
                Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
            ) {
                scene.note(format!(
                    "{}: mesh '{name}' primitive {pi} draws {mode:?}, which Canopy does not render; it is skipped",
                    path.display()
                ));
            }
            if prim.morph_targets().next().is_some() {
                scene.note(format!(
                    "{}: mesh '{name}' primitive {pi} has morph targets, which Canopy does not apply; its base shape is kept",
                    path.display()
                ));
            }
        }
    }
    let skinned = doc.nodes().filter(|n| n.skin().is_some()).count();
    if skinned > 0 {
        scene.note(format!(
            "{}: {skinned} nodes are skinned, which Canopy does not apply; their meshes keep the bind pose",
            path.display()
        ));
    }
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
