//! Archives taken apart, mutated with their checksums recomputed, and exercised.

use super::{poke, poke_record, seed_inputs, Rng, SEED_SCENE};
use anyhow::{Context, Result};
use canopy::convert::{convert, ConvertOptions};
use canopy::integrator::cone::ConeSettings;
use canopy::integrator::Settings;
use canopy::render::{render, RenderOptions};
use canopy_format::records::*;
use std::path::Path;

/// An archive taken apart: header, raw (decompressed) pages, tables.
#[derive(Clone)]
pub struct Parts {
    pub header: Header,
    /// Decompressed page bytes (page header, nodes, triangles, vertices, ...).
    pub pages: Vec<Vec<u8>>,
    pub entries: Vec<PageEntry>,
    pub materials: Vec<MaterialRecord>,
    pub cameras: Vec<CameraRecord>,
    pub lights: Vec<LightRecord>,
    pub instances: Vec<InstanceRecord>,
    pub textures: Vec<TextureRecord>,
    pub environment: Vec<EnvironmentRecord>,
    pub notes: Vec<NoteRecord>,
    /// Decoded texels of each texture tile.
    pub tiles: Vec<Vec<u8>>,
    /// Tile indices in the order their frames lie in the file (the converter writes them
    /// as the pyramid is built, before the pages).
    pub tile_order: Vec<u32>,
}

impl Parts {
    pub fn read(path: &Path) -> Result<Parts> {
        let a = canopy_format::Archive::open(path)?;
        let entries = a.entries()?;
        let pages = (0..a.page_count())
            .map(|i| {
                let e = entries[i as usize];
                Ok(zstd::bulk::decompress(
                    a.page_bytes(i)?,
                    e.raw_len as usize,
                )?)
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Parts {
            header: a.header,
            pages,
            entries,
            materials: a.materials.clone(),
            cameras: a.cameras.clone(),
            lights: a.lights.clone(),
            instances: a.instances.clone(),
            textures: a.textures.clone(),
            environment: a.environment.into_iter().collect(),
            notes: a.notes.iter().map(|n| NoteRecord::new(n)).collect(),
            tiles: (0..a.tile_count())
                .map(|i| Ok(a.read_tile(i)?))
                .collect::<Result<Vec<_>>>()?,
            tile_order: {
                let mut order: Vec<u32> = (0..a.tile_count()).collect();
                order.sort_by_key(|&i| a.tile_entries()[i as usize].offset);
                order
            },
        })
    }

    /// Writes the archive back with every offset, length, alignment and checksum recomputed,
    /// so only the mutation itself is wrong.
    pub fn assemble(&self) -> Vec<u8> {
        let mut out = vec![0u8; 256];
        let align = |out: &mut Vec<u8>| out.resize(out.len().next_multiple_of(ALIGN as usize), 0);
        let mut tiles = vec![<TileEntry as bytemuck::Zeroable>::zeroed(); self.tiles.len()];
        for &i in &self.tile_order {
            let e = canopy_format::encode_tile(&self.tiles[i as usize], 1).expect("zstd");
            align(&mut out);
            tiles[i as usize] = TileEntry {
                offset: out.len() as u64,
                compressed_len: e.bytes.len() as u32,
                raw_len: canopy_format::TILE_BYTES,
                checksum: e.checksum,
                reserved: [0; 8],
            };
            out.extend_from_slice(&e.bytes);
        }
        let mut entries = self.entries.clone();
        for (e, raw) in entries.iter_mut().zip(&self.pages) {
            let z = zstd::bulk::compress(raw, 1).expect("zstd");
            align(&mut out);
            e.offset = out.len() as u64;
            e.compressed_len = z.len() as u32;
            e.checksum = xxhash_rust::xxh3::xxh3_64(&z);
            e.seal();
            out.extend_from_slice(&z);
        }
        align(&mut out);
        align(&mut out);
        let mut h = self.header;
        let table =
            |out: &mut Vec<u8>, bytes: &[u8], count: usize, size: usize, t: &mut TableRef| {
                t.offset = out.len() as u64;
                t.count = count as u32;
                t.record_size = size as u32;
                out.extend_from_slice(bytes);
            };
        let materials = bytemuck::cast_slice(&self.materials);
        table(
            &mut out,
            materials,
            self.materials.len(),
            std::mem::size_of::<MaterialRecord>(),
            &mut h.materials,
        );
        let cameras = bytemuck::cast_slice(&self.cameras);
        table(&mut out, cameras, self.cameras.len(), 128, &mut h.cameras);
        let lights = bytemuck::cast_slice(&self.lights);
        table(&mut out, lights, self.lights.len(), 96, &mut h.lights);
        // Paged instance records travel in the pages: the table counts them in no bytes.
        let (count, size) = match self.header.features & Features::PAGED_INSTANCES {
            0 => (self.instances.len(), 64),
            _ => (self.header.instances.count as usize, 0),
        };
        let instances = bytemuck::cast_slice(&self.instances);
        table(&mut out, instances, count, size, &mut h.instances);
        let textures = bytemuck::cast_slice(&self.textures);
        table(&mut out, textures, self.textures.len(), 64, &mut h.textures);
        let tile_table = bytemuck::cast_slice(&tiles);
        table(&mut out, tile_table, tiles.len(), 32, &mut h.tiles);
        let environment = bytemuck::cast_slice(&self.environment);
        table(
            &mut out,
            environment,
            self.environment.len(),
            256,
            &mut h.environment,
        );
        h.notes = self.notes.len() as u32;
        out.extend_from_slice(bytemuck::cast_slice(&self.notes));
        h.tables_checksum = xxhash_rust::xxh3::xxh3_64(&out[h.materials.offset as usize..]);
        align(&mut out);
        let pages = bytemuck::cast_slice(&entries);
        table(&mut out, pages, entries.len(), 96, &mut h.pages);
        h.file_len = out.len() as u64;
        h.header_checksum = 0;
        h.header_checksum = xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&h));
        out[..256].copy_from_slice(bytemuck::bytes_of(&h));
        out
    }
}

/// Mutates an archive; returns the class index.
pub fn mutate_archive(base: &Parts, raw: &[u8], rng: &mut Rng) -> (usize, Vec<u8>) {
    let class = rng.below(7);
    let mut p = base.clone();
    let bytes = match class {
        0 => {
            let mut b = raw.to_vec();
            for _ in 0..1 + rng.below(8) {
                let i = rng.below(b.len());
                b[i] ^= 1 << rng.below(8);
            }
            b
        }
        1 => {
            let mut b = raw.to_vec();
            if rng.below(2) == 0 {
                b.truncate(rng.below(b.len()));
            } else {
                b.extend((0..1 + rng.below(4096)).map(|_| rng.u64() as u8));
            }
            b
        }
        2 => {
            let mut h = bytemuck::bytes_of(&p.header).to_vec();
            // Leave the table refs and checksums to `assemble`: poke the described fields.
            let fields = [
                8usize, 16, 24, 32, 40, 48, 64, 68, 72, 76, 80, 84, 88, 92, 96, 100, 184, 200, 252,
            ];
            let at = *rng.pick(&fields);
            poke(&mut h[at..at + 4], rng);
            p.header = bytemuck::pod_read_unaligned(&h);
            p.assemble()
        }
        3 => {
            poke_record(&mut p.entries, rng);
            p.assemble()
        }
        4 => {
            match rng.below(7) {
                0 => poke_record(&mut p.materials, rng),
                1 => poke_record(&mut p.cameras, rng),
                2 => poke_record(&mut p.lights, rng),
                3 => poke_record(&mut p.textures, rng),
                4 => poke_record(&mut p.environment, rng),
                5 => poke_record(&mut p.notes, rng),
                _ => poke_record(&mut p.instances, rng),
            }
            p.assemble()
        }
        5 => {
            let i = rng.below(p.pages.len());
            let page = &mut p.pages[i];
            for _ in 0..1 + rng.below(3) {
                // Past the 32-byte page header most of the time: nodes, triangles, vertices.
                let skip = if rng.below(8) == 0 { 0 } else { 32 };
                poke(&mut page[skip..], rng);
            }
            p.assemble()
        }
        _ => {
            rewire(&mut p, rng);
            p.assemble()
        }
    };
    (class, bytes)
}

/// Structural lies that pass every checksum: a DAG inside a page, a page linked twice, a
/// parent link made a cycle.
fn rewire(p: &mut Parts, rng: &mut Rng) {
    let i = rng.below(p.pages.len());
    let n = p.entries[i].node_count as usize;
    let node = |k: usize| 32 + k * 128;
    match rng.below(4) {
        0 if n >= 3 => {
            // Node k: inner, children k+1 and k+2 (a DAG when repeated).
            for k in 0..n.saturating_sub(2) {
                let at = node(k);
                p.pages[i][at + 38] = 0;
                p.pages[i][at + 12..at + 16].copy_from_slice(&((k + 1) as u32).to_le_bytes());
                p.pages[i][at + 16..at + 20].copy_from_slice(&((k + 2) as u32).to_le_bytes());
            }
        }
        1 => {
            let j = rng.below(p.entries.len());
            p.entries[i].parent_page = j as u32;
            p.entries[i].level = p.entries[j].level.wrapping_add(rng.below(3) as u16);
        }
        2 if n >= 2 => {
            // Two nodes point at the same child.
            let (a, b) = (rng.below(n), rng.below(n));
            let link = p.pages[i][node(a) + 12..node(a) + 20].to_vec();
            p.pages[i][node(b) + 12..node(b) + 20].copy_from_slice(&link);
            p.pages[i][node(b) + 38] = p.pages[i][node(a) + 38];
        }
        _ => {
            let j = rng.below(p.entries.len());
            p.entries.swap(i, j);
        }
    }
}

/// Options for a tiny render of `archive` into `dir`.
pub fn tiny_render(archive: &Path, dir: &Path, integrator: Settings) -> RenderOptions {
    RenderOptions {
        archive: archive.to_path_buf(),
        output: dir.join("r.exr"),
        integrator,
        spp: 1,
        time: None,
        noise: None,
        mem_budget: None,
        width: Some(12),
        height: Some(8),
        camera: None,
        seed: 0,
        threads: Some(2),
        max_depth: Some(4),
        texture_filter: canopy::texture::TextureFilter::Trilinear,
        pixel_split: None,
        env: None,
        display: None,
        crop: None,
        preview: false,
        exposure: 1.0,
        stats: None,
        node_stats: true,
        lights: None,
        progress: false,
    }
}

/// Both integrators, the cone one with small settings for tiny renders.
pub fn integrators() -> [Settings; 2] {
    let cone = ConeSettings {
        samples: Some(64),
        photons: Some(64),
        edge_rays: 2,
        ..ConeSettings::default()
    };
    [Settings::Path, Settings::Cone(cone)]
}

/// Open, verify every page, and render with every integrator that takes the archive (PBGI
/// refuses an instanced one). Errors are fine; the caller catches panics.
pub fn exercise_archive(path: &Path, dir: &Path) -> Result<()> {
    let a = canopy_format::Archive::open(path)?;
    let mut s = canopy::inspect::summarize(&a)?;
    let verified = canopy::inspect::verify(&a, &mut s, false);
    // Integrators that refuse the archive are asked once, for their error.
    let usable: Vec<Settings> = integrators()
        .into_iter()
        .filter(|i| i.check_archive(&a).is_ok())
        .collect();
    drop(a);
    for integrator in usable {
        render(&tiny_render(path, dir, integrator))?;
    }
    verified
}

/// The scene-file environment one seed archive carries.
const SEED_SKY: &str = "\n[environment]\nsky = true\nsun_elevation_degrees = 30.0\n";

/// The archives mutations start from: the seed inputs converted with small pages, so they
/// have several pages and child-page links.
pub fn seed_archives(dir: &Path) -> Result<Vec<(Parts, Vec<u8>)>> {
    let inputs = seed_inputs();
    let mut out = Vec::new();
    for main in ["s.glb", "m.obj", "a.ply", "i.glb"] {
        let d = dir.join(format!("seed-{main}"));
        std::fs::create_dir_all(&d)?;
        for (name, bytes) in &inputs {
            std::fs::write(d.join(name), bytes)?;
        }
        // One seed carries a sky for the environment table's mutations.
        let sky = if main == "m.obj" { SEED_SKY } else { "" };
        std::fs::write(d.join("scene.toml"), format!("{SEED_SCENE}{sky}"))?;
        let path = d.join("x.canopy");
        let mut o = ConvertOptions::new(vec![d.join(main)], path.clone());
        o.page_nodes = 3;
        if !main.ends_with(".glb") {
            o.scene = Some(d.join("scene.toml"));
        }
        convert(&o).with_context(|| format!("converting the seed {main}"))?;
        out.push((Parts::read(&path)?, std::fs::read(&path)?));
    }
    // The instanced seed again, as 2.6 wrote it (its records in the instance table).
    let (paged, _) = out.last().expect("the instanced seed");
    let table = super::paged::unpaged(paged);
    let bytes = table.assemble();
    out.push((table, bytes));
    Ok(out)
}
