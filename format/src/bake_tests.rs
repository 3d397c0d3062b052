//! Tests of the bake file's writer and reader.

use super::*;

fn block() -> BakedBlock {
    let value = |index| CoefValue {
        index,
        rgb: [1.0, -2.0, 0.5],
    };
    BakedBlock {
        nodes: vec![BakedNode::default(); 3],
        patch_of: Vec::new(),
        patches: Vec::new(),
        coefs: CoefBlock {
            records: vec![
                CoefRecord {
                    node: 0,
                    kind: CoefRecord::AVERAGE,
                    first: 0,
                    count: 2,
                },
                CoefRecord {
                    node: 2,
                    kind: CoefRecord::DETAIL,
                    first: 2,
                    count: 1,
                },
            ],
            values: vec![value(0), value(5), value(23)],
        },
    }
}

/// A coefficient section reads back as written; each way a record can lie about its
/// node, kind, values or indices is refused.
#[test]
fn coefficient_sections_round_trip_and_bad_records_are_refused() {
    let good = block();
    let c = &good.coefs;
    let mut raw = Vec::new();
    raw.extend_from_slice(&(c.records.len() as u32).to_le_bytes());
    raw.extend_from_slice(&(c.values.len() as u32).to_le_bytes());
    raw.extend_from_slice(bytemuck::cast_slice(&c.records));
    raw.extend_from_slice(bytemuck::cast_slice(&c.values));
    assert_eq!(raw.len() as u64, c.bytes());
    assert_eq!(&read_coefs(&raw).unwrap(), c);
    assert!(read_coefs(&raw[..raw.len() - 1]).is_err());
    assert!(check_coefs(&good, 2).is_ok());
    assert!(check_coefs(&good, 1).is_err(), "index 23 needs 6·2² texels");
    let bad: [&dyn Fn(&mut CoefBlock); 7] = [
        &|c| c.records[1].node = 0,
        &|c| c.records[1].node = 3,
        &|c| c.records[0].kind = 2,
        &|c| c.records[1].first = 1,
        &|c| c.records[1].count = 2,
        &|c| c.values.swap(0, 1),
        &|c| c.values[2].rgb[1] = f32::NAN,
    ];
    for (k, spoil) in bad.iter().enumerate() {
        let mut b = good.clone();
        spoil(&mut b.coefs);
        assert!(check_coefs(&b, 2).is_err(), "spoiled record {k} accepted");
    }
}
