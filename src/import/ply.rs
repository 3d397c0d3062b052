//! PLY, ASCII and binary (either endianness): vertices with x, y, z and optional nx, ny, nz;
//! faces as a vertex-index list, fan-triangulated, or triangle strips (`tristrips`, with −1
//! restarts, as Stanford's scans ship). Vertex positions are held in memory
//! (12 bytes a vertex, 24 with normals) up to `IN_MEMORY_BYTES`, beyond that in an unnamed
//! temporary file read through a map whose pages are released as faces stream, so an
//! indexed mesh of any size imports in bounded memory; faces stream.

use super::{context, make_tri, raw_mesh_material, SceneDesc, SceneFile, TriangleSink};
use anyhow::{bail, Context, Result};
use std::io::{BufRead, BufReader};
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
    fn decode(self, b: &[u8], big: bool) -> f64 {
        macro_rules! num {
            ($t:ty) => {{
                let a = b[..std::mem::size_of::<$t>()].try_into().unwrap();
                (if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as f64
            }};
        }
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => num!(i16),
            Self::U16 => num!(u16),
            Self::I32 => num!(i32),
            Self::U32 => num!(u32),
            Self::F32 => num!(f32),
            Self::F64 => num!(f64),
        }
    }
}

#[derive(Debug)]
struct Property {
    name: String,
    ty: Scalar,
    /// Count type for list properties.
    list: Option<Scalar>,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: u64,
    props: Vec<Property>,
}

#[derive(PartialEq)]
enum Encoding {
    Ascii,
    Binary { big: bool },
}

fn read_header(r: &mut impl BufRead, path: &Path) -> Result<(Encoding, Vec<Element>)> {
    let mut line = String::new();
    let mut next = |line: &mut String| -> Result<bool> {
        Ok(super::read_line(r, line).map_err(context(path))? > 0)
    };
    if !next(&mut line)? || line.trim_end() != "ply" {
        bail!("{}: not a PLY file (missing 'ply' magic)", path.display());
    }
    let mut enc = None;
    let mut elems: Vec<Element> = Vec::new();
    loop {
        if !next(&mut line)? {
            bail!("{}: truncated PLY header (no end_header)", path.display());
        }
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.as_slice() {
            ["end_header"] => break,
            ["format", f, _] => {
                enc = Some(match *f {
                    "ascii" => Encoding::Ascii,
                    "binary_little_endian" => Encoding::Binary { big: false },
                    "binary_big_endian" => Encoding::Binary { big: true },
                    _ => bail!("{}: unknown PLY format '{f}'", path.display()),
                })
            }
            ["element", name, count] => elems.push(Element {
                name: name.to_string(),
                count: count
                    .parse()
                    .with_context(|| format!("{}: bad element count '{count}'", path.display()))?,
                props: Vec::new(),
            }),
            ["property", "list", ct, it, name] => {
                let (Some(ct), Some(it)) = (Scalar::parse(ct), Scalar::parse(it)) else {
                    bail!(
                        "{}: bad list property types in '{}'",
                        path.display(),
                        line.trim()
                    );
                };
                let Some(e) = elems.last_mut() else {
                    bail!("{}: property before any element", path.display())
                };
                e.props.push(Property {
                    name: name.to_string(),
                    ty: it,
                    list: Some(ct),
                });
            }
            ["property", ty, name] => {
                let Some(ty) = Scalar::parse(ty) else {
                    bail!("{}: unknown property type '{ty}'", path.display())
                };
                let Some(e) = elems.last_mut() else {
                    bail!("{}: property before any element", path.display())
                };
                e.props.push(Property {
                    name: name.to_string(),
                    ty,
                    list: None,
                });
            }
            ["comment", ..] | ["obj_info", ..] | [] => {}
            _ => bail!(
                "{}: unexpected PLY header line '{}'",
                path.display(),
                line.trim()
            ),
        }
    }
    let Some(enc) = enc else {
        bail!("{}: PLY header has no format line", path.display())
    };
    Ok((enc, elems))
}

/// Reads one element record's values: scalars as one value each, lists as their items.
struct RecordReader<R> {
    r: R,
    enc: Encoding,
    tokens: Vec<String>,
    at: usize,
    buf: [u8; 8],
}

impl<R: BufRead> RecordReader<R> {
    fn scalar(&mut self, ty: Scalar) -> std::io::Result<f64> {
        match self.enc {
            Encoding::Binary { big } => {
                let n = ty.size();
                self.r.read_exact(&mut self.buf[..n])?;
                Ok(ty.decode(&self.buf, big))
            }
            Encoding::Ascii => {
                while self.at >= self.tokens.len() {
                    let mut line = String::new();
                    if super::read_line(&mut self.r, &mut line)? == 0 {
                        return Err(std::io::ErrorKind::UnexpectedEof.into());
                    }
                    self.tokens = line.split_whitespace().map(str::to_string).collect();
                    self.at = 0;
                }
                self.at += 1;
                self.tokens[self.at - 1].parse().map_err(|_| {
                    std::io::Error::new(
                        std::io::ErrorKind::InvalidData,
                        format!("'{}' is not a number", self.tokens[self.at - 1]),
                    )
                })
            }
        }
    }
}

/// Most bytes of vertex arrays kept in memory; larger ones go to a mapped temporary file.
const IN_MEMORY_BYTES: u64 = 64 << 20;
/// Faces between releases of a mapped vertex file's resident pages.
const RELEASE_EVERY: u64 = 1 << 20;

/// One vertex attribute array while it is read, in memory or in a temporary file.
enum VertexSink {
    Mem(Vec<[f32; 3]>),
    File(std::io::BufWriter<std::fs::File>),
}

/// A vertex attribute array once read.
enum Vertices {
    Mem(Vec<[f32; 3]>),
    Mapped(memmap2::Mmap),
}

impl VertexSink {
    fn new(count: u64) -> std::io::Result<VertexSink> {
        Ok(if count * 12 > IN_MEMORY_BYTES {
            VertexSink::File(std::io::BufWriter::with_capacity(
                1 << 20,
                tempfile::tempfile()?,
            ))
        } else {
            VertexSink::Mem(Vec::with_capacity(count as usize))
        })
    }

    fn push(&mut self, v: [f32; 3]) -> std::io::Result<()> {
        match self {
            VertexSink::Mem(m) => m.push(v),
            VertexSink::File(w) => std::io::Write::write_all(w, bytemuck::bytes_of(&v))?,
        }
        Ok(())
    }

    fn finish(self) -> std::io::Result<Vertices> {
        Ok(match self {
            VertexSink::Mem(m) => Vertices::Mem(m),
            VertexSink::File(w) => {
                let f = w.into_inner().map_err(|e| e.into_error())?;
                // SAFETY: the file is unnamed and ours alone; nothing else can change it.
                Vertices::Mapped(unsafe { memmap2::Mmap::map(&f)? })
            }
        })
    }
}

impl Vertices {
    fn as_slice(&self) -> &[[f32; 3]] {
        match self {
            Vertices::Mem(m) => m,
            // A map is page aligned, so f32 triples read in place.
            Vertices::Mapped(m) => bytemuck::cast_slice(&m[..]),
        }
    }

    /// Drops a mapped file's pages from the resident set (they fault back in when read).
    fn release(&self) {
        #[cfg(unix)]
        if let Vertices::Mapped(m) = self {
            // SAFETY: a private read-only map of an unnamed file: after MADV_DONTNEED a read
            // faults the same bytes back in.
            unsafe {
                m.unchecked_advise(memmap2::UncheckedAdvice::DontNeed).ok();
            }
        }
    }
}

type FaceFn<'a> = dyn FnMut(u64, &[u32], &[[f32; 3]], &[[f32; 3]]) -> Result<()> + 'a;

pub fn import(
    path: &Path,
    scene: &mut SceneDesc,
    file: &SceneFile,
    sink: &mut dyn TriangleSink,
) -> Result<u64> {
    let material = raw_mesh_material(path, scene, file)?;
    let mut count = 0u64;
    let has_normals = parse(path, &mut |i, idx, pos, nrm| {
        for k in 2..idx.len() {
            let tri = [idx[0], idx[k - 1], idx[k]];
            let p = tri.map(|v| pos[v as usize]);
            let n = (!nrm.is_empty()).then(|| tri.map(|v| nrm[v as usize]));
            sink.push(make_tri(p, n, material, &|| {
                format!("{}: face {i}", path.display())
            })?)?;
            count += 1;
        }
        Ok(())
    })?;
    scene.has_normals |= has_normals;
    Ok(count)
}

/// Vertex positions and triangle index triples.
pub type IndexedMesh = (Vec<[f32; 3]>, Vec<[u32; 3]>);

/// An indexed triangle mesh read whole (for tools that transform small meshes).
pub fn read_mesh(path: &Path) -> Result<IndexedMesh> {
    let mut tris = Vec::new();
    let mut verts = Vec::new();
    parse(path, &mut |i, idx, pos, _| {
        if verts.is_empty() {
            verts = pos.to_vec();
        }
        for k in 2..idx.len() {
            if let Some(p) = [idx[0], idx[k - 1], idx[k]]
                .iter()
                .flat_map(|&v| pos[v as usize])
                .find(|x| !x.is_finite())
            {
                bail!(
                    "{}: face {i}: non-finite vertex coordinate {p}",
                    path.display()
                );
            }
            tris.push([idx[0], idx[k - 1], idx[k]]);
        }
        Ok(())
    })?;
    Ok((verts, tris))
}

/// A strip's restart (PLY's −1 in a `tristrips` list).
const RESTART: u32 = u32::MAX;

/// The triangles of a `tristrips` list (runs separated by `RESTART`): each run's k-th
/// triangle is (s_k, s_k+1, s_k+2), every other one turned to keep the winding; those
/// with a repeated vertex (a strip's joins) are left out.
fn strip_triangles(idx: &[u32], mut tri: impl FnMut([u32; 3]) -> Result<()>) -> Result<()> {
    for run in idx.split(|&v| v == RESTART) {
        for (k, w) in run.windows(3).enumerate() {
            let [a, b, c] = [w[0], w[1], w[2]];
            if a == b || b == c || a == c {
                continue;
            }
            tri(if k % 2 == 0 { [a, b, c] } else { [b, a, c] })?;
        }
    }
    Ok(())
}

/// Warns of vertex properties Canopy does not apply (colours, texture coordinates), naming
/// them and what is used instead.
fn name_unread(path: &Path, e: &Element) {
    let unread: Vec<&str> = e
        .props
        .iter()
        .map(|p| p.name.as_str())
        .filter(|n| {
            matches!(
                *n,
                "red"
                    | "green"
                    | "blue"
                    | "alpha"
                    | "diffuse_red"
                    | "diffuse_green"
                    | "diffuse_blue"
                    | "r"
                    | "g"
                    | "b"
                    | "s"
                    | "t"
                    | "u"
                    | "v"
                    | "texture_u"
                    | "texture_v"
            )
        })
        .collect();
    if !unread.is_empty() {
        eprintln!(
            "warning: {}: its vertices carry {}, which Canopy does not apply; the material is one colour",
            path.display(),
            unread.join(", ")
        );
    }
}

/// Streams a PLY file: vertices are read into memory, each face is handed to `face` with
/// its validated indices. Returns whether the vertices carried normals.
fn parse(path: &Path, face: &mut FaceFn) -> Result<bool> {
    let f = std::fs::File::open(path).map_err(context(path))?;
    let file_len = f.metadata().map_err(context(path))?.len();
    let mut r = BufReader::with_capacity(1 << 20, f);
    let (enc, elems) = read_header(&mut r, path)?;
    let mut rr = RecordReader {
        r,
        enc,
        tokens: Vec::new(),
        at: 0,
        buf: [0; 8],
    };
    let mut pos = Vertices::Mem(Vec::new());
    let mut nrm = Vertices::Mem(Vec::new());
    let mut has_normals = false;
    let mut vals = Vec::new();
    for e in &elems {
        // Every record takes at least a byte: refuse absurd counts before allocating.
        if e.count > file_len {
            bail!(
                "{}: element '{}' claims {} records, more than the file's {file_len} bytes",
                path.display(),
                e.name,
                e.count
            );
        }
        let eof = |i: u64| {
            move |err: std::io::Error| {
                anyhow::anyhow!(
                    "{}: truncated or malformed PLY: {} {i} of {}: {err}",
                    path.display(),
                    e.name,
                    e.count
                )
            }
        };
        match e.name.as_str() {
            "vertex" => {
                let find = |n: &str| e.props.iter().position(|p| p.name == n && p.list.is_none());
                let (Some(x), Some(y), Some(z)) = (find("x"), find("y"), find("z")) else {
                    bail!("{}: vertex element lacks x, y, z", path.display());
                };
                let normals = match (find("nx"), find("ny"), find("nz")) {
                    (Some(a), Some(b), Some(c)) => Some([a, b, c]),
                    _ => None,
                };
                name_unread(path, e);
                let io = |err: std::io::Error| {
                    anyhow::anyhow!("{}: vertex spill file: {err}", path.display())
                };
                let mut pos_in = VertexSink::new(e.count).map_err(io)?;
                let mut nrm_in =
                    VertexSink::new(if normals.is_some() { e.count } else { 0 }).map_err(io)?;
                for i in 0..e.count {
                    vals.clear();
                    for p in &e.props {
                        if let Some(ct) = p.list {
                            let n = rr.scalar(ct).map_err(eof(i))? as usize;
                            for _ in 0..n {
                                rr.scalar(p.ty).map_err(eof(i))?;
                            }
                            vals.push(0.0);
                        } else {
                            vals.push(rr.scalar(p.ty).map_err(eof(i))?);
                        }
                    }
                    pos_in
                        .push([vals[x] as f32, vals[y] as f32, vals[z] as f32])
                        .map_err(io)?;
                    if let Some([a, b, c]) = normals {
                        nrm_in
                            .push([vals[a] as f32, vals[b] as f32, vals[c] as f32])
                            .map_err(io)?;
                    }
                }
                (pos, nrm) = (pos_in.finish().map_err(io)?, nrm_in.finish().map_err(io)?);
                has_normals = normals.is_some();
            }
            "face" | "tristrips" => {
                let strips = e.name == "tristrips";
                let Some(li) = e.props.iter().position(|p| {
                    p.list.is_some() && (p.name == "vertex_indices" || p.name == "vertex_index")
                }) else {
                    bail!(
                        "{}: {} element lacks a vertex_indices list",
                        path.display(),
                        e.name
                    );
                };
                let mut idx: Vec<u32> = Vec::new();
                let (ps, ns) = (pos.as_slice(), nrm.as_slice());
                for i in 0..e.count {
                    for (pi, p) in e.props.iter().enumerate() {
                        if let Some(ct) = p.list {
                            let n = rr.scalar(ct).map_err(eof(i))?;
                            if pi == li {
                                idx.clear();
                            }
                            for _ in 0..n as usize {
                                let v = rr.scalar(p.ty).map_err(eof(i))?;
                                if pi != li {
                                    continue;
                                }
                                if strips && v == -1.0 {
                                    idx.push(RESTART);
                                } else if v < 0.0 || v >= ps.len() as f64 {
                                    bail!(
                                        "{}: {} {i}: vertex index {v} out of range ({} vertices)",
                                        path.display(),
                                        e.name,
                                        ps.len()
                                    );
                                } else {
                                    idx.push(v as u32);
                                }
                            }
                        } else {
                            rr.scalar(p.ty).map_err(eof(i))?;
                        }
                    }
                    match strips {
                        true => strip_triangles(&idx, |tri| face(i, &tri, ps, ns))?,
                        false => face(i, &idx, ps, ns)?,
                    }
                    if i % RELEASE_EVERY == RELEASE_EVERY - 1 {
                        pos.release();
                        nrm.release();
                    }
                }
            }
            _ => {
                for i in 0..e.count {
                    for p in &e.props {
                        let n = match p.list {
                            Some(ct) => rr.scalar(ct).map_err(eof(i))? as usize,
                            None => 1,
                        };
                        for _ in 0..n {
                            rr.scalar(p.ty).map_err(eof(i))?;
                        }
                    }
                }
            }
        }
    }
    Ok(has_normals)
}
