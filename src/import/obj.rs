//! Wavefront OBJ with MTL: `v` (with an optional `r g b` colour), `vn`, `vt`, `f` (polygons
//! fan-triangulated, negative indices allowed), `usemtl`, `mtllib`. Vertices are held in memory; faces stream.

use super::{
    context, make_tri, raw_mesh_material, srgb_unorm16, SceneDesc, SceneFile, TextureSource,
    TriangleSink, WHITE,
};
use anyhow::{bail, Result};
use canopy_format::{name_bytes, MaterialRecord, TextureRecord};
use std::collections::HashMap;
use std::io::BufReader;
use std::path::Path;

fn floats<const N: usize>(w: &[&str], path: &Path, line: usize) -> Result<[f32; N]> {
    let mut out = [0.0; N];
    if w.len() < N {
        bail!("{}:{line}: expected {N} numbers", path.display());
    }
    for (o, s) in out.iter_mut().zip(w) {
        *o = s
            .parse()
            .map_err(|_| anyhow::anyhow!("{}:{line}: '{s}' is not a number", path.display()))?;
    }
    Ok(out)
}

/// Largest MTL file read.
const MAX_MTL: u64 = 64 << 20;

/// Numbered lines (from 1), each at most `MAX_LINE` bytes.
fn lines<'a>(
    f: std::fs::File,
    path: &'a Path,
) -> impl Iterator<Item = (usize, Result<String>)> + 'a {
    let mut r = BufReader::with_capacity(1 << 20, f);
    let mut ln = 0;
    std::iter::from_fn(move || {
        let mut line = String::new();
        ln += 1;
        match super::read_line(&mut r, &mut line) {
            Ok(0) => None,
            Ok(_) => Some((ln, Ok(line))),
            Err(e) => Some((ln, Err(anyhow::anyhow!("{}:{ln}: {e}", path.display())))),
        }
    })
}

/// An MTL material and the images its `map_Kd` and `map_Ke` name.
type MtlEntry = (MaterialRecord, [Option<TextureSource>; 2]);

/// The image file a `map_*` statement names: its last word (options such as `-s u v w`
/// come first), relative to the library's directory.
fn map_file(dir: &Path, rest: &[&str], srgb: bool) -> Option<TextureSource> {
    let name = rest.last()?;
    Some(TextureSource {
        file: Some(dir.join(name.replace('\\', "/"))),
        bytes: None,
        name: name.to_string(),
        srgb,
        wrap: [TextureRecord::WRAP_REPEAT; 2],
    })
}

/// Parses an MTL library into named materials (Kd, Ks, Ns, Ke, Ni, d/Tr, map_Kd, map_Ke).
fn read_mtl(path: &Path) -> Result<HashMap<String, MtlEntry>> {
    super::check_regular(path, MAX_MTL, "material library")?;
    let f = std::fs::File::open(path).map_err(context(path))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut out = HashMap::new();
    let mut cur: Option<(String, MtlEntry)> = None;
    for (ln, line) in lines(f, path) {
        let line = line?;
        let w: Vec<&str> = line.split_whitespace().collect();
        let Some((&key, rest)) = w.split_first() else {
            continue;
        };
        if key == "newmtl" {
            if let Some((n, m)) = cur.take() {
                out.insert(n, m);
            }
            let name = rest.join(" ");
            let mut m = super::default_material(&name);
            m.name = name_bytes(&name);
            cur = Some((name, (m, [None, None])));
            continue;
        }
        let Some((_, (m, maps))) = cur.as_mut() else {
            continue;
        };
        let ln = ln + 1;
        match key {
            // MTL files in the wild stray outside glTF's ranges (Kd 1.2, Ni 0): clamp what is
            // finite, as the renderer would; NaN and infinities stay and are refused later.
            "Kd" => {
                let [r, g, b] = floats::<3>(rest, path, ln)?.map(|c| c.clamp(0.0, 1.0));
                m.base_color = [r, g, b, 1.0];
            }
            "Ke" => {
                m.emission = floats::<3>(rest, path, ln)?.map(|c| if c < 0.0 { 0.0 } else { c })
            }
            "Ns" => {
                // Phong exponent to GGX roughness: α² = 2/(Ns+2), roughness = √α.
                let [ns] = floats::<1>(rest, path, ln)?;
                m.roughness = (2.0 / (ns.max(0.0) + 2.0)).sqrt().sqrt();
            }
            "Ks" => {
                let [r, g, b] = floats::<3>(rest, path, ln)?;
                let s = r.max(g).max(b);
                m.specular = if s > 0.0 { 1.0 } else { 0.0 };
                if s > 0.0 {
                    m.specular_color = [r / s, g / s, b / s];
                }
            }
            "Ni" => {
                let [ni] = floats::<1>(rest, path, ln)?;
                m.ior = if ni < 1.0 {
                    1.5
                } else if ni > 1e3 {
                    1e3
                } else {
                    ni
                };
            }
            "d" => m.transmission = 1.0 - floats::<1>(rest, path, ln)?[0].clamp(0.0, 1.0),
            "Tr" => m.transmission = floats::<1>(rest, path, ln)?[0].clamp(0.0, 1.0),
            "map_Kd" | "map_Ke" => {
                m.flags |= MaterialRecord::TEXTURED;
                maps[(key == "map_Ke") as usize] = map_file(dir, rest, true);
            }
            _ => {}
        }
    }
    if let Some((n, m)) = cur {
        out.insert(n, m);
    }
    Ok(out)
}

/// The colour of vertex `count` (numbered from 1) from its `v` line's words after x, y, z:
/// `r g b` (the common extension, sRGB-encoded values in [0, 1] as MeshLab writes them),
/// or white. `colours` stays empty until a vertex has a colour.
fn vertex_colour(
    colours: &mut Vec<[u16; 4]>,
    count: usize,
    rest: &[&str],
    path: &Path,
    ln: usize,
) -> Result<()> {
    if rest.len() < 6 {
        if !colours.is_empty() {
            colours.push(WHITE);
        }
        return Ok(());
    }
    let rgb = floats::<3>(&rest[3..6], path, ln)?;
    colours.resize(count - 1, WHITE);
    let [r, g, b] = rgb.map(srgb_unorm16);
    colours.push([r, g, b, u16::MAX]);
    Ok(())
}

pub fn import(
    path: &Path,
    scene: &mut SceneDesc,
    file: &SceneFile,
    sink: &mut dyn TriangleSink,
) -> Result<u64> {
    let f = std::fs::File::open(path).map_err(context(path))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut pos: Vec<[f32; 3]> = Vec::new();
    let mut nrm: Vec<[f32; 3]> = Vec::new();
    let mut tex: Vec<[f32; 2]> = Vec::new();
    // Empty until a vertex has a colour; then one per vertex.
    let mut colour: Vec<[u16; 4]> = Vec::new();
    let mut library: HashMap<String, MtlEntry> = HashMap::new();
    let mut indices: HashMap<String, u32> = HashMap::new();
    let mut material = None;
    // The mesh's default material, made when a face first needs it.
    let mut default = None;
    // Material names met in `usemtl` that no library read defines.
    let mut unknown = std::collections::HashSet::new();
    let mut count = 0u64;
    let mut face: Vec<(u32, Option<u32>, Option<u32>)> = Vec::new();
    for (ln, line) in lines(f, path) {
        let line = line?;
        let w: Vec<&str> = line.split_whitespace().collect();
        let Some((&key, rest)) = w.split_first() else {
            continue;
        };
        match key {
            "v" => {
                pos.push(floats::<3>(rest, path, ln)?);
                vertex_colour(&mut colour, pos.len(), rest, path, ln)?;
            }
            "vn" => nrm.push(floats::<3>(rest, path, ln)?),
            // OBJ's t runs up the image, glTF's (and the archive's) down.
            "vt" => {
                let [u, v] = floats::<2>(&rest[..rest.len().min(2)], path, ln)?;
                tex.push([u, 1.0 - v]);
            }
            "mtllib" => {
                for lib in rest {
                    let at = dir.join(lib);
                    if !at.exists() {
                        scene.note(format!(
                            "{}:{ln}: material library {} not found; faces naming its materials take the mesh's default material",
                            path.display(),
                            at.display()
                        ));
                        continue;
                    }
                    library.extend(read_mtl(&at)?);
                }
            }
            "usemtl" => {
                let name = rest.join(" ");
                let Some((m, maps)) = library.get(&name) else {
                    if unknown.insert(name.clone()) {
                        scene.note(format!(
                            "{}:{ln}: material '{name}' is in no material library read; its faces take the mesh's default material",
                            path.display()
                        ));
                    }
                    material = None;
                    continue;
                };
                if m.flags & MaterialRecord::TEXTURED != 0 {
                    scene.textured = true;
                }
                material = Some(match indices.get(&name) {
                    Some(&i) => i,
                    None => {
                        let mut m = *m;
                        let slots = [MaterialRecord::BASE_COLOR, MaterialRecord::EMISSIVE];
                        for (slot, src) in slots.into_iter().zip(maps) {
                            if let Some(src) = src {
                                m.textures[slot] = scene.add_texture(src.clone())?;
                            }
                        }
                        let i = scene.add_material(m)?;
                        indices.insert(name, i);
                        i
                    }
                });
            }
            "f" => {
                let mat = match (material, default) {
                    (Some(m), _) => m,
                    (None, Some(d)) => *material.insert(d),
                    (None, None) => {
                        let d = raw_mesh_material(path, scene, file, !colour.is_empty())?;
                        *material.insert(*default.insert(d))
                    }
                };
                face.clear();
                for v in rest {
                    let mut parts = v.split('/');
                    let resolve = |s: Option<&str>, n: usize| -> Result<Option<u32>> {
                        let Some(s) = s.filter(|s| !s.is_empty()) else {
                            return Ok(None);
                        };
                        let i: i64 = s.parse().map_err(|_| {
                            anyhow::anyhow!("{}:{ln}: bad index '{s}'", path.display())
                        })?;
                        let r = if i < 0 { n as i64 + i } else { i - 1 };
                        if r < 0 || r >= n as i64 {
                            bail!(
                                "{}:{ln}: index {i} out of range ({n} defined so far)",
                                path.display()
                            );
                        }
                        Ok(Some(r as u32))
                    };
                    let Some(p) = resolve(parts.next(), pos.len())? else {
                        bail!("{}:{ln}: face without vertex index", path.display())
                    };
                    let t = resolve(parts.next(), tex.len())?;
                    face.push((p, t, resolve(parts.next(), nrm.len())?));
                }
                for k in 2..face.len() {
                    let tri = [face[0], face[k - 1], face[k]];
                    let p = tri.map(|(v, _, _)| pos[v as usize]);
                    let n = tri
                        .iter()
                        .all(|(_, _, n)| n.is_some())
                        .then(|| tri.map(|(_, _, n)| nrm[n.unwrap() as usize]));
                    if n.is_some() {
                        scene.has_normals = true;
                    }
                    let mut t = make_tri(p, n, mat, &|| format!("{}:{ln}", path.display()))?;
                    if tri.iter().all(|(_, t, _)| t.is_some()) {
                        t.uv = tri.map(|(_, t, _)| tex[t.unwrap() as usize]);
                        scene.has_uvs = true;
                        if t.uv.iter().flatten().any(|x| !x.is_finite()) {
                            bail!("{}:{ln}: non-finite texture coordinate", path.display());
                        }
                    }
                    if !colour.is_empty() {
                        t.colour = tri.map(|(v, _, _)| colour[v as usize]);
                        scene.has_colours = true;
                    }
                    sink.push(t)?;
                    count += 1;
                }
            }
            _ => {}
        }
    }
    Ok(count)
}
