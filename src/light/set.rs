//! A light set: the changes a render or a relight makes to an archive's lights, read from a
//! small TOML file (`--lights`). Lamps (emissive materials) are scaled and tinted, punctual
//! lights moved, re-aimed, re-coloured, switched off or added, the environment made
//! stronger or turned. The changes are made to the archive's records before its lights are
//! gathered, so every reader of the lights sees the same set.
//!
//! ```toml
//! [[emitter]]              # every lamp triangle of a material, by name or index
//! material = "Light"
//! strength = 2.0           # factor on its emission (0 switches it off)
//! color = [1.0, 0.8, 0.6]  # factor per channel
//!
//! [[light]]                # an archive's punctual light, by name or index
//! light = 0
//! position = [0.0, 1.9, 0.0]
//!
//! [[light]]                # without `light`: a light added
//! type = "spot"            # point, spot or directional
//! position = [0.5, 1.5, 0.5]
//! direction = [0.0, -1.0, 0.0]
//! intensity = 4.0          # candela (point, spot) or lux (directional), as glTF
//! color = [1.0, 0.9, 0.8]
//!
//! [environment]
//! strength = 0.5
//! rotate = 90.0            # degrees about +Y
//! ```

use anyhow::{bail, Context, Result};
use canopy_format::{name_str, Archive, LightRecord, MaterialRecord};
use serde::Deserialize;
use std::path::{Path, PathBuf};

#[derive(Deserialize, Debug, Clone, Default)]
#[serde(deny_unknown_fields)]
pub struct LightSet {
    #[serde(default)]
    emitter: Vec<EmitterChange>,
    #[serde(default)]
    light: Vec<PunctualChange>,
    environment: Option<EnvironmentChange>,
    /// The file it was read from, for errors.
    #[serde(skip)]
    path: PathBuf,
}

/// A material or light named by its name or its index.
#[derive(Deserialize, Debug, Clone)]
#[serde(untagged)]
enum Name {
    Index(usize),
    Name(String),
}

#[derive(Deserialize, Debug, Clone)]
#[serde(deny_unknown_fields)]
struct EmitterChange {
    material: Name,
    strength: Option<f32>,
    color: Option<[f32; 3]>,
}

#[derive(Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
enum Kind {
    Point,
    Spot,
    Directional,
}

#[derive(Deserialize, Debug, Clone)]
#[serde(deny_unknown_fields)]
struct PunctualChange {
    light: Option<Name>,
    #[serde(rename = "type")]
    kind: Option<Kind>,
    position: Option<[f32; 3]>,
    direction: Option<[f32; 3]>,
    intensity: Option<f32>,
    color: Option<[f32; 3]>,
    /// Spot cone half-angles in radians, as glTF.
    inner_cone: Option<f32>,
    outer_cone: Option<f32>,
}

#[derive(Deserialize, Debug, Clone)]
#[serde(deny_unknown_fields)]
struct EnvironmentChange {
    strength: Option<f32>,
    rotate: Option<f32>,
}

impl LightSet {
    pub fn read(path: &Path) -> Result<LightSet> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read the light set", path.display()))?;
        let mut set: LightSet = toml::from_str(&text)
            .with_context(|| format!("{}: not a light set", path.display()))?;
        set.path = path.to_path_buf();
        set.check()?;
        Ok(set)
    }

    /// Values no light can take: negative or non-finite factors and intensities, zero
    /// directions, spot cones out of order.
    fn check(&self) -> Result<()> {
        let f = self.path.display();
        let bad = |what: String| -> Result<()> { bail!("{f}: {what}") };
        let factor = |v: f32| v.is_finite() && v >= 0.0;
        for (i, e) in self.emitter.iter().enumerate() {
            let c = e.color.unwrap_or([1.0; 3]);
            if !factor(e.strength.unwrap_or(1.0)) || !c.iter().all(|&v| factor(v)) {
                bad(format!(
                    "emitter {i}: strength and color must be finite and ≥ 0"
                ))?;
            }
        }
        for (i, l) in self.light.iter().enumerate() {
            let c = l.color.unwrap_or([1.0; 3]);
            if !factor(l.intensity.unwrap_or(1.0)) || !c.iter().all(|&v| factor(v)) {
                bad(format!(
                    "light {i}: intensity and color must be finite and ≥ 0"
                ))?;
            }
            let p = l.position.unwrap_or_default();
            let d = l.direction.unwrap_or([0.0, -1.0, 0.0]);
            if !p.iter().chain(&d).all(|v| v.is_finite()) || d == [0.0; 3] {
                bad(format!(
                    "light {i}: position and direction must be finite, direction not zero"
                ))?;
            }
            let inner = l.inner_cone.unwrap_or(0.0);
            let outer = l.outer_cone.unwrap_or(std::f32::consts::FRAC_PI_4);
            if !(0.0..=outer).contains(&inner) || outer > std::f32::consts::FRAC_PI_2 {
                bad(format!(
                    "light {i}: spot cones must satisfy 0 ≤ inner_cone ≤ outer_cone ≤ π/2"
                ))?;
            }
            if l.light.is_none() && (l.kind.is_none() || l.intensity.is_none()) {
                bad(format!(
                    "light {i}: a light added (no `light = ` naming one of the archive's) needs `type` and `intensity`"
                ))?;
            }
            if l.light.is_none() && l.kind != Some(Kind::Directional) && l.position.is_none() {
                bad(format!(
                    "light {i}: a point or spot light added needs `position`"
                ))?;
            }
        }
        if let Some(e) = &self.environment {
            let ok = factor(e.strength.unwrap_or(1.0)) && e.rotate.unwrap_or(0.0).is_finite();
            if !ok {
                bad("environment: strength must be finite and ≥ 0, rotate finite".into())?;
            }
        }
        Ok(())
    }

    /// A light set sent as JSON (the TOML file's tables as JSON objects); `origin` names
    /// it in errors.
    pub fn from_json(text: &str, origin: &str) -> Result<LightSet> {
        let mut set: LightSet =
            serde_json::from_str(text).with_context(|| format!("{origin}: not a light set"))?;
        set.path = origin.into();
        set.check()?;
        Ok(set)
    }

    /// The environment's change: a factor on its strength and degrees to turn it about
    /// +Y (1 and 0 where the set leaves it), None where the set has no [environment].
    pub fn environment_change(&self) -> Option<(f32, f32)> {
        self.environment
            .as_ref()
            .map(|e| (e.strength.unwrap_or(1.0), e.rotate.unwrap_or(0.0)))
    }

    /// Makes the changes to `archive`'s material, light and environment records.
    pub fn apply(&self, archive: &mut Archive) -> Result<()> {
        self.apply_to_lamps(&mut archive.materials, &mut archive.lights)?;
        if let Some((strength, rotate)) = self.environment_change() {
            let Some(env) = archive.environment.as_mut() else {
                bail!(
                    "{}: [environment] changes the archive's environment, and {} carries none (give one to the scene file, or light the render with --env or --sky and their strength and rotation flags)",
                    self.path.display(),
                    archive.path().display()
                );
            };
            env.strength *= strength;
            env.rotate_degrees += rotate;
        }
        Ok(())
    }

    /// Makes the changes to an archive's material and light records (its lamps and
    /// punctual lights), leaving its environment as it is.
    pub fn apply_to_lamps(
        &self,
        materials: &mut [MaterialRecord],
        lights: &mut Vec<LightRecord>,
    ) -> Result<()> {
        let f = self.path.display();
        for e in &self.emitter {
            let names: Vec<String> = materials.iter().map(|m| name_str(&m.name)).collect();
            let i = find(&e.material, &names)
                .with_context(|| format!("{f}: {}", missing("material", &e.material, &names)))?;
            let m = &mut materials[i];
            if m.emission.iter().all(|&v| v <= 0.0) {
                bail!(
                    "{f}: material {i} ({}) emits no light, so it has no lamp to change (only the archive's lamps can be scaled)",
                    names[i]
                );
            }
            let c = e.color.unwrap_or([1.0; 3]);
            let s = e.strength.unwrap_or(1.0);
            for (e, c) in m.emission.iter_mut().zip(c) {
                *e *= s * c;
            }
        }
        for l in &self.light {
            match &l.light {
                Some(name) => {
                    let names: Vec<String> = lights.iter().map(|r| name_str(&r.name)).collect();
                    let i = find(name, &names)
                        .with_context(|| format!("{f}: {}", missing("light", name, &names)))?;
                    l.change(&mut lights[i]);
                }
                None => {
                    let mut r: LightRecord = bytemuck::Zeroable::zeroed();
                    r.color = [1.0; 3];
                    r.direction = [0.0, -1.0, 0.0];
                    r.outer_cone = std::f32::consts::FRAC_PI_4;
                    l.change(&mut r);
                    lights.push(r);
                }
            }
        }
        Ok(())
    }
}

impl PunctualChange {
    fn change(&self, r: &mut LightRecord) {
        if let Some(k) = self.kind {
            r.kind = match k {
                Kind::Point => LightRecord::POINT,
                Kind::Spot => LightRecord::SPOT,
                Kind::Directional => LightRecord::DIRECTIONAL,
            };
        }
        if let Some(p) = self.position {
            r.position = p;
        }
        if let Some(d) = self.direction {
            let n = glam::Vec3::from(d).normalize();
            r.direction = n.into();
        }
        if let Some(i) = self.intensity {
            r.intensity = i;
        }
        if let Some(c) = self.color {
            r.color = c;
        }
        if let Some(a) = self.inner_cone {
            r.inner_cone = a;
        }
        if let Some(a) = self.outer_cone {
            r.outer_cone = a;
        }
    }
}

fn find(name: &Name, names: &[String]) -> Option<usize> {
    match name {
        Name::Index(i) => (*i < names.len()).then_some(*i),
        Name::Name(s) => names.iter().position(|n| n == s),
    }
}

fn missing(what: &str, name: &Name, names: &[String]) -> String {
    let asked = match name {
        Name::Index(i) => format!("{what} {i}"),
        Name::Name(s) => format!("{what} {s:?}"),
    };
    let list = if names.is_empty() {
        "none".to_string()
    } else {
        names
            .iter()
            .enumerate()
            .map(|(i, n)| format!("{i} {n:?}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    format!("the archive has no {asked} (its {what}s: {list})")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(text: &str) -> Result<LightSet> {
        let mut s: LightSet = toml::from_str(text)?;
        s.path = "set.toml".into();
        s.check()?;
        Ok(s)
    }

    #[test]
    fn light_sets_are_read_and_their_mistakes_named() {
        let s = set("[[emitter]]\nmaterial = \"Light\"\nstrength = 2\n[[light]]\ntype = \"point\"\nposition = [0, 1, 0]\nintensity = 3\n").unwrap();
        assert_eq!(s.emitter.len(), 1);
        assert_eq!(s.light[0].kind, Some(Kind::Point));
        for (text, says) in [
            ("[[emitter]]\nmaterial = 0\nstrength = -1\n", "emitter 0"),
            (
                "[[light]]\ntype = \"spot\"\nintensity = 1\n",
                "needs `position`",
            ),
            (
                "[[light]]\nposition = [0, 0, 0]\n",
                "needs `type` and `intensity`",
            ),
            (
                "[[light]]\nlight = 0\ndirection = [0, 0, 0]\n",
                "direction not zero",
            ),
            (
                "[[light]]\nlight = 0\ninner_cone = 1\nouter_cone = 0.5\n",
                "spot cones",
            ),
            ("[environment]\nstrength = nan\n", "environment"),
        ] {
            let e = format!("{:#}", set(text).unwrap_err());
            assert!(e.contains(says), "{text:?}: {e}");
        }
        assert!(set("[[lamp]]\n").is_err(), "unknown tables are refused");
    }
}
