//! Running moments of a stream of values.

/// Running mean and variance (Welford) of a stream of values (luminances: a PBGI record's gathers, a pixel's samples).
#[derive(Clone, Copy, Debug, Default)]
pub struct Moments {
    pub count: u64,
    mean: f64,
    m2: f64,
}

impl Moments {
    /// The moments of `ys`.
    pub fn of(ys: impl IntoIterator<Item = f32>) -> Moments {
        let mut m = Moments::default();
        ys.into_iter().for_each(|y| m.add(y));
        m
    }

    pub fn add(&mut self, y: f32) {
        self.count += 1;
        let d = y as f64 - self.mean;
        self.mean += d / self.count as f64;
        self.m2 += d * (y as f64 - self.mean);
    }

    /// The sample variance (0 below two samples).
    pub fn variance(&self) -> f64 {
        match self.count {
            0 | 1 => 0.0,
            k => self.m2 / (k - 1) as f64,
        }
    }
}
