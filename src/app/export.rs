//! `render --export-mesh FILE.glb`: the drawn mesh ([`crate::lod::mesh`]) as binary glTF
//! 2.0, which Blender, game engines and GIS 3D viewers open. glTF is right-handed with y
//! up, as the world is (x east, y up, z south), and in metres, as the world is for
//! georeferenced inputs; the terrain's CRS, origin and spacing go in the scene's
//! `extras`, so that a reader can place the mesh back on the map.

use crate::app::outputs::{write_atomic, TerrainFacts};
use crate::lod::mesh::DrawnMesh;
use serde_json::json;
use std::path::Path;

/// The GLB bytes of `mesh`.
pub fn glb_bytes(mesh: &DrawnMesh, facts: &TerrainFacts) -> Vec<u8> {
    let mut bin: Vec<u8> = Vec::with_capacity(mesh.positions.len() * 12 + mesh.indices.len() * 4);
    for p in &mesh.positions {
        for c in p {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    let positions_len = bin.len();
    for i in &mesh.indices {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let indices_len = bin.len() - positions_len;
    // glTF requires POSITION's bounds.
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in &mesh.positions {
        for c in 0..3 {
            lo[c] = lo[c].min(p[c]);
            hi[c] = hi[c].max(p[c]);
        }
    }
    if mesh.positions.is_empty() {
        (lo, hi) = ([0.0; 3], [0.0; 3]);
    }
    let doc = json!({
        "asset": { "version": "2.0", "generator": concat!("vkterrain ", env!("CARGO_PKG_VERSION")) },
        "scene": 0,
        "scenes": [{ "nodes": [0], "extras": { "terrain": facts, "up": "+y", "units": "metres (world units)" } }],
        "nodes": [{ "mesh": 0, "name": "terrain" }],
        "meshes": [{ "name": "terrain", "primitives": [{ "attributes": { "POSITION": 0 }, "indices": 1, "mode": 4 }] }],
        "buffers": [{ "byteLength": bin.len() }],
        "bufferViews": [
            { "buffer": 0, "byteOffset": 0, "byteLength": positions_len, "target": 34962 },
            { "buffer": 0, "byteOffset": positions_len, "byteLength": indices_len, "target": 34963 }
        ],
        "accessors": [
            { "bufferView": 0, "componentType": 5126, "count": mesh.positions.len(), "type": "VEC3", "min": lo, "max": hi },
            { "bufferView": 1, "componentType": 5125, "count": mesh.indices.len(), "type": "SCALAR" }
        ]
    });
    let mut json_chunk = serde_json::to_vec(&doc).expect("a JSON value serialises");
    // Chunks are 4-byte aligned: JSON padded with spaces, binary with zeros.
    while !json_chunk.len().is_multiple_of(4) {
        json_chunk.push(b' ');
    }
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json_chunk.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_chunk.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json_chunk);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

/// Writes `mesh` to `path` (atomically: a failed run leaves no half file).
pub fn write_glb(path: &Path, mesh: &DrawnMesh, facts: &TerrainFacts) -> anyhow::Result<()> {
    let bytes = glb_bytes(mesh, facts);
    if bytes.len() > u32::MAX as usize {
        anyhow::bail!("{}: the mesh needs {} bytes, more than a GLB file holds (4 GiB)", path.display(), bytes.len());
    }
    write_atomic(path, |tmp| std::fs::write(tmp, &bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display())))
}
