//! An archive's instances as the tracer uses them: the object-to-world transform and its
//! inverse in f32 (the inverse taken in f64). Applying them to rays is the tracer's
//! (`trace::instance`).

use canopy_format::InstanceRecord;

/// Rows of a 3×4 affine map, column 3 the translation.
pub type Rows = [[f32; 4]; 3];

#[derive(Clone, Debug)]
pub struct Instance {
    /// The instance's number in the archive (what light keys are taken by).
    pub number: u32,
    /// The page whose node 0 is the prototype's root.
    pub page: u32,
    pub to_world: Rows,
    pub to_object: Rows,
    /// How the transform scales curvature: |det|^−⅓ (exact for uniform scales).
    pub curvature_scale: f32,
}

impl Instance {
    /// Instance `number`, of record `r` (its transform checked invertible when the record
    /// was read).
    pub fn new(number: u32, r: &InstanceRecord) -> Instance {
        let m = r.matrix();
        let det = r.det();
        let cof = canopy_format::cofactors3(&r.linear());
        // The inverse of the linear part is the transposed cofactor matrix over det.
        let inv: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| cof[j][i] / det));
        let to_object = std::array::from_fn(|i| {
            let t = -(0..3).map(|j| inv[i][j] * m[j][3]).sum::<f64>();
            [
                inv[i][0] as f32,
                inv[i][1] as f32,
                inv[i][2] as f32,
                t as f32,
            ]
        });
        Instance {
            number,
            page: r.prototype_page,
            to_world: m.map(|row| row.map(|x| x as f32)),
            to_object,
            curvature_scale: det.abs().cbrt().recip() as f32,
        }
    }
}
