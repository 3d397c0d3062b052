//! PLY, ASCII and binary (either endianness): vertices with x, y, z and optional nx, ny, nz
//! and colours (red, green, blue, alpha);
//! faces as a vertex-index list, fan-triangulated, or triangle strips (`tristrips`, with −1
//! restarts, as Stanford's scans ship). Each vertex array (positions 12 bytes a vertex,
//! normals 12, colours 8) is held in memory up to `IN_MEMORY_BYTES`, beyond that in an unnamed
//! temporary file read through a map whose pages are released as faces stream, so an
//! indexed mesh of any size imports in bounded memory; faces stream.

use super::{
    context, make_tri, raw_mesh_material, srgb_unorm16, unorm16, SceneDesc, SceneFile, TriangleSink,
};
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
enum VertexSink<T> {
    Mem(Vec<T>),
    File(std::io::BufWriter<std::fs::File>),
}

/// A vertex attribute array once read.
enum Vertices<T> {
    Mem(Vec<T>),
    Mapped(memmap2::Mmap),
}

impl<T: bytemuck::Pod> VertexSink<T> {
    fn new(count: u64) -> std::io::Result<VertexSink<T>> {
        Ok(
            if count * std::mem::size_of::<T>() as u64 > IN_MEMORY_BYTES {
                VertexSink::File(std::io::BufWriter::with_capacity(
                    1 << 20,
                    tempfile::tempfile()?,
                ))
            } else {
                VertexSink::Mem(Vec::with_capacity(count as usize))
            },
        )
    }

    fn push(&mut self, v: T) -> std::io::Result<()> {
        match self {
            VertexSink::Mem(m) => m.push(v),
            VertexSink::File(w) => std::io::Write::write_all(w, bytemuck::bytes_of(&v))?,
        }
        Ok(())
    }

    fn finish(self) -> std::io::Result<Vertices<T>> {
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

impl<T: bytemuck::Pod> Vertices<T> {
    fn as_slice(&self) -> &[T] {
        match self {
            Vertices::Mem(m) => m,
            // A map is page aligned, so the values read in place.
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

/// A PLY file's vertex arrays: positions, and normals and colours where it has them
/// (empty otherwise).
struct VertexArrays {
    pos: Vertices<[f32; 3]>,
    nrm: Vertices<[f32; 3]>,
    /// Linear unorm16 RGBA.
    colour: Vertices<[u16; 4]>,
}

impl VertexArrays {
    fn none() -> VertexArrays {
        VertexArrays {
            pos: Vertices::Mem(Vec::new()),
            nrm: Vertices::Mem(Vec::new()),
            colour: Vertices::Mem(Vec::new()),
        }
    }

    fn attrs(&self) -> Attrs<'_> {
        Attrs {
            pos: self.pos.as_slice(),
            nrm: self.nrm.as_slice(),
            colour: self.colour.as_slice(),
        }
    }

    fn release(&self) {
        self.pos.release();
        self.nrm.release();
        self.colour.release();
    }
}

/// The vertex arrays a face indexes (normals and colours empty when the file has none).
#[derive(Clone, Copy)]
struct Attrs<'a> {
    pos: &'a [[f32; 3]],
    nrm: &'a [[f32; 3]],
    colour: &'a [[u16; 4]],
}

type FaceFn<'a> = dyn FnMut(u64, &[u32], Attrs) -> Result<()> + 'a;

pub fn import(
    path: &Path,
    scene: &mut SceneDesc,
    file: &SceneFile,
    sink: &mut dyn TriangleSink,
) -> Result<u64> {
    let mut material = None;
    let mut count = 0u64;
    let found = parse(path, &mut |i, idx, a| {
        let material = match material {
            Some(m) => m,
            None => *material.insert(raw_mesh_material(path, scene, file, !a.colour.is_empty())?),
        };
        for k in 2..idx.len() {
            let tri = [idx[0], idx[k - 1], idx[k]];
            let p = tri.map(|v| a.pos[v as usize]);
            let n = (!a.nrm.is_empty()).then(|| tri.map(|v| a.nrm[v as usize]));
            let mut t = make_tri(p, n, material, &|| format!("{}: face {i}", path.display()))?;
            if !a.colour.is_empty() {
                t.colour = tri.map(|v| a.colour[v as usize]);
            }
            sink.push(t)?;
            count += 1;
        }
        Ok(())
    })?;
    scene.has_normals |= found.normals;
    scene.has_colours |= found.colours;
    if let Some(note) = found.unread {
        scene.note(note);
    }
    Ok(count)
}

/// Vertex positions and triangle index triples.
pub type IndexedMesh = (Vec<[f32; 3]>, Vec<[u32; 3]>);

/// An indexed triangle mesh read whole (for tools that transform small meshes).
pub fn read_mesh(path: &Path) -> Result<IndexedMesh> {
    let mut tris = Vec::new();
    let mut verts = Vec::new();
    parse(path, &mut |i, idx, a| {
        let pos = a.pos;
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

/// The note for vertex properties Canopy does not apply (texture coordinates: PLY names
/// no image for them), naming them and what is used instead.
fn name_unread(path: &Path, e: &Element) -> Option<String> {
    let unread: Vec<&str> = e
        .props
        .iter()
        .map(|p| p.name.as_str())
        .filter(|n| matches!(*n, "s" | "t" | "u" | "v" | "texture_u" | "texture_v"))
        .collect();
    (!unread.is_empty()).then(|| {
        format!(
            "{}: its vertices carry {}, which Canopy does not apply; the material is one colour",
            path.display(),
            unread.join(", ")
        )
    })
}

/// Which optional vertex attributes a PLY file carried, and the note for those it does
/// not apply.
#[derive(Default)]
struct Found {
    normals: bool,
    colours: bool,
    unread: Option<String>,
}

/// Where a vertex record's colour channels are, and what one of them reads as 1.
struct ColourProps {
    rgb: [usize; 3],
    alpha: Option<usize>,
    /// The largest value of the channels' type (255 for uchar; 1 for floats).
    one: f64,
}

impl ColourProps {
    /// The colour properties of a vertex element: `red`, `green`, `blue` (or `diffuse_red`…,
    /// or `r`, `g`, `b`) and `alpha`, all scalars of one type.
    fn find(e: &Element) -> Option<ColourProps> {
        let find = |n: &str| e.props.iter().position(|p| p.name == n && p.list.is_none());
        let rgb = [
            ["red", "green", "blue"],
            ["diffuse_red", "diffuse_green", "diffuse_blue"],
            ["r", "g", "b"],
        ]
        .iter()
        .find_map(|names| {
            let [r, g, b] = names.map(find);
            Some([r?, g?, b?])
        })?;
        let one = match e.props[rgb[0]].ty {
            Scalar::U8 | Scalar::I8 => 255.0,
            Scalar::U16 | Scalar::I16 => 65535.0,
            Scalar::U32 | Scalar::I32 => u32::MAX as f64,
            Scalar::F32 | Scalar::F64 => 1.0,
        };
        Some(ColourProps {
            rgb,
            alpha: find("alpha"),
            one,
        })
    }

    /// A record's colour: sRGB-encoded display values (as scanners and MeshLab write
    /// them) made linear; alpha is linear.
    fn read(&self, vals: &[f64]) -> [u16; 4] {
        let c = |i: usize| (vals[i] / self.one) as f32;
        let [r, g, b] = self.rgb.map(|i| srgb_unorm16(c(i)));
        [r, g, b, self.alpha.map_or(u16::MAX, |a| unorm16(c(a)))]
    }
}

/// Reads a vertex element's records: positions, and normals and colours where the element
/// has them.
fn read_vertices<R: BufRead>(
    rr: &mut RecordReader<R>,
    e: &Element,
    path: &Path,
) -> Result<(VertexArrays, Found)> {
    let find = |n: &str| e.props.iter().position(|p| p.name == n && p.list.is_none());
    let (Some(x), Some(y), Some(z)) = (find("x"), find("y"), find("z")) else {
        bail!("{}: vertex element lacks x, y, z", path.display());
    };
    let normals = match (find("nx"), find("ny"), find("nz")) {
        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
        _ => None,
    };
    let colours = ColourProps::find(e);
    let io = |err: std::io::Error| anyhow::anyhow!("{}: vertex spill file: {err}", path.display());
    let eof = |i: u64, err: std::io::Error| {
        anyhow::anyhow!(
            "{}: truncated or malformed PLY: vertex {i} of {}: {err}",
            path.display(),
            e.count
        )
    };
    let count_if = |on: bool| if on { e.count } else { 0 };
    let mut pos_in = VertexSink::new(e.count).map_err(io)?;
    let mut nrm_in = VertexSink::new(count_if(normals.is_some())).map_err(io)?;
    let mut colour_in = VertexSink::new(count_if(colours.is_some())).map_err(io)?;
    let mut vals = Vec::with_capacity(e.props.len());
    for i in 0..e.count {
        vals.clear();
        for p in &e.props {
            if let Some(ct) = p.list {
                let n = rr.scalar(ct).map_err(|err| eof(i, err))? as usize;
                for _ in 0..n {
                    rr.scalar(p.ty).map_err(|err| eof(i, err))?;
                }
                vals.push(0.0);
            } else {
                vals.push(rr.scalar(p.ty).map_err(|err| eof(i, err))?);
            }
        }
        let triple = |[a, b, c]: [usize; 3]| [vals[a] as f32, vals[b] as f32, vals[c] as f32];
        pos_in.push(triple([x, y, z])).map_err(io)?;
        if let Some(n) = normals {
            nrm_in.push(triple(n)).map_err(io)?;
        }
        if let Some(c) = &colours {
            colour_in.push(c.read(&vals)).map_err(io)?;
        }
    }
    let arrays = VertexArrays {
        pos: pos_in.finish().map_err(io)?,
        nrm: nrm_in.finish().map_err(io)?,
        colour: colour_in.finish().map_err(io)?,
    };
    let found = Found {
        normals: normals.is_some(),
        colours: colours.is_some(),
        unread: name_unread(path, e),
    };
    Ok((arrays, found))
}

/// Streams a PLY file: vertices are read into memory, each face is handed to `face` with
/// its validated indices. Returns which vertex attributes the file carried.
fn parse(path: &Path, face: &mut FaceFn) -> Result<Found> {
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
    let mut arrays = VertexArrays::none();
    let mut found = Found::default();
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
            "vertex" => (arrays, found) = read_vertices(&mut rr, e, path)?,
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
                let a = arrays.attrs();
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
                                } else if v < 0.0 || v >= a.pos.len() as f64 {
                                    bail!(
                                        "{}: {} {i}: vertex index {v} out of range ({} vertices)",
                                        path.display(),
                                        e.name,
                                        a.pos.len()
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
                        true => strip_triangles(&idx, |tri| face(i, &tri, a))?,
                        false => face(i, &idx, a)?,
                    }
                    if i % RELEASE_EVERY == RELEASE_EVERY - 1 {
                        arrays.release();
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
    Ok(found)
}
