//! The binary glTF container: its two chunks, apart and together.

/// Splits a .glb into its JSON and BIN chunks.
pub fn glb_split(b: &[u8]) -> Option<(serde_json::Value, Vec<u8>)> {
    let jlen = u32::from_le_bytes(b.get(12..16)?.try_into().ok()?) as usize;
    let json = serde_json::from_slice(b.get(20..20 + jlen)?).ok()?;
    let bin = b
        .get(20 + jlen + 8..)
        .map(<[u8]>::to_vec)
        .unwrap_or_default();
    Some((json, bin))
}

/// A .glb of these chunks (the JSON padded with spaces, no BIN chunk when `bin` is empty).
pub fn glb_join(json: &serde_json::Value, bin: &[u8]) -> Vec<u8> {
    let mut j = serde_json::to_vec(json).expect("json");
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut out = Vec::new();
    let total = 12 + 8 + j.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(j.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&j);
    if !bin.is_empty() {
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(bin);
    }
    out
}
