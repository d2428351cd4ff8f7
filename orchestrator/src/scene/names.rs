//! Scene values that name one of a fixed set (`method = "ugimp"`, `lattice = "fcc"`, faces):
//! deserialised straight into their typed enums, the engine's own where it has one
//! ([`continuum::SchemeKind`], [`continuum::solver::TimeIntegrator`], [`md_worker::LatticeKind`],
//! [`md_worker::StressSampling`]) and the scene's where the scene's set differs (a deformation
//! of `auto`, a face `roller`).
//!
//! A name outside the set fails deserialisation with an [`Unknown`] (the field, the value and
//! what is allowed), which [`super::parse`] turns into the scene's usual message with the
//! dotted key and its line (or `--set`): the same message validation gave when these values
//! were strings.

use serde::de::{self, Deserializer, MapAccess, Visitor};
use serde::{Deserialize, Serialize, Serializer};
use std::fmt;

/// A value of a scene key that takes one name of a fixed set.
pub trait SceneName: Sized + Copy + PartialEq + 'static {
    /// The key's own name (its last dotted part), for values inside tagged tables whose error
    /// carries only the table's place.
    const FIELD: &'static str;
    /// Scene names and their values, in the order messages list them.
    const NAMES: &'static [(&'static str, Self)];
    /// What a message says is allowed.
    fn allowed() -> String {
        format!("allowed: {}", Self::NAMES.iter().map(|(n, _)| format!("{n:?}")).collect::<Vec<_>>().join(", "))
    }
    fn from_scene_name(name: &str) -> Option<Self> {
        Self::NAMES.iter().find(|(n, _)| *n == name).map(|(_, v)| *v)
    }
    fn scene_name(self) -> &'static str {
        Self::NAMES.iter().find(|(_, v)| *v == self).map(|(n, _)| *n).unwrap_or("?")
    }
}

/// Marks a deserialisation error as an unknown name (fields separated by the same byte).
const MARK: char = '\u{1f}';

/// An unknown name: what [`super::parse`] needs to write the message.
#[derive(Debug, Clone, PartialEq)]
pub struct Unknown {
    /// The key's own name, empty where the error's place is the value itself (faces).
    pub field: String,
    /// The value as written in messages (`"magic"`).
    pub value: String,
    pub allowed: String,
}

impl Unknown {
    fn encode(&self) -> String {
        format!("{MARK}{}{MARK}{}{MARK}{}", self.field, self.value, self.allowed)
    }

    /// The unknown name a deserialisation error message carries, if it is one.
    pub fn decode(message: &str) -> Option<Unknown> {
        let rest = message.strip_prefix(MARK)?;
        let mut parts = rest.splitn(3, MARK);
        Some(Unknown { field: parts.next()?.into(), value: parts.next()?.into(), allowed: parts.next()?.into() })
    }
}

fn unknown<E: de::Error>(field: &str, value: &str, allowed: String) -> E {
    E::custom(Unknown { field: field.into(), value: format!("{value:?}"), allowed }.encode())
}

/// `#[serde(with = "named")]` for a [`SceneName`] field.
pub mod named {
    use super::*;

    pub fn serialize<T: SceneName, S: Serializer>(v: &T, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(v.scene_name())
    }

    pub fn deserialize<'de, T: SceneName, D: Deserializer<'de>>(d: D) -> Result<T, D::Error> {
        let name = String::deserialize(d)?;
        T::from_scene_name(&name).ok_or_else(|| unknown(T::FIELD, &name, T::allowed()))
    }
}

impl SceneName for continuum::SchemeKind {
    const FIELD: &'static str = "method";
    const NAMES: &'static [(&'static str, Self)] = continuum::SchemeKind::NAMES;
    fn allowed() -> String {
        format!("allowed: {}", Self::NAMES.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", "))
    }
}

impl SceneName for continuum::solver::TimeIntegrator {
    const FIELD: &'static str = "integrator";
    const NAMES: &'static [(&'static str, Self)] = &[
        ("dhakal", continuum::solver::TimeIntegrator::Dhakal),
        ("leapfrog", continuum::solver::TimeIntegrator::Leapfrog),
        ("usl", continuum::solver::TimeIntegrator::Usl),
        ("usf", continuum::solver::TimeIntegrator::Usf),
        ("stormer-verlet", continuum::solver::TimeIntegrator::StormerVerlet),
        ("implicit-trapezoidal", continuum::solver::TimeIntegrator::ImplicitTrapezoidal),
    ];
    fn allowed() -> String {
        "allowed: \"dhakal\" (Ch. 3.1 cycle), \"leapfrog\", \"usl\" (symplectic Euler), \"usf\" (update stress first), \"stormer-verlet\", \"implicit-trapezoidal\"".into()
    }
}

impl SceneName for continuum::solver::GradientCorrection {
    const FIELD: &'static str = "gradient_correction";
    const NAMES: &'static [(&'static str, Self)] = &[
        ("none", continuum::solver::GradientCorrection::None),
        ("constant", continuum::solver::GradientCorrection::Constant),
        ("linear", continuum::solver::GradientCorrection::Linear),
    ];
}

impl SceneName for super::TlmpmForm {
    const FIELD: &'static str = "tlmpm_form";
    const NAMES: &'static [(&'static str, Self)] =
        &[("total-lagrangian", super::TlmpmForm::TotalLagrangian), ("moving-mesh", super::TlmpmForm::MovingMesh)];
}

impl SceneName for continuum::solver::NullspaceFilter {
    const FIELD: &'static str = "nullspace_filter";
    const NAMES: &'static [(&'static str, Self)] = &[
        ("none", continuum::solver::NullspaceFilter::None),
        ("local", continuum::solver::NullspaceFilter::Local),
        ("global-svd", continuum::solver::NullspaceFilter::GlobalSvd),
    ];
}

impl SceneName for continuum::solver::implicit::JacobianKind {
    const FIELD: &'static str = "jacobian";
    const NAMES: &'static [(&'static str, Self)] = &[
        ("analytic", continuum::solver::implicit::JacobianKind::Analytic),
        ("finite-difference", continuum::solver::implicit::JacobianKind::FiniteDifference),
    ];
}

/// `scheme.artificial_viscosity`: which form (its coefficients are keys of their own).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ViscosityForm {
    None,
    /// Ch. 6.3.
    Linear,
    /// (7.8)-(7.10).
    Tensor,
}

impl SceneName for ViscosityForm {
    const FIELD: &'static str = "artificial_viscosity";
    const NAMES: &'static [(&'static str, Self)] =
        &[("none", ViscosityForm::None), ("linear", ViscosityForm::Linear), ("tensor", ViscosityForm::Tensor)];
}

impl SceneName for md_worker::LatticeKind {
    const FIELD: &'static str = "lattice";
    const NAMES: &'static [(&'static str, Self)] =
        &[("fcc", md_worker::LatticeKind::Fcc), ("bcc", md_worker::LatticeKind::Bcc), ("sc", md_worker::LatticeKind::Sc)];
}

impl SceneName for md_worker::StressSampling {
    const FIELD: &'static str = "stress_sampling";
    const NAMES: &'static [(&'static str, Self)] =
        &[("last", md_worker::StressSampling::Last), ("average", md_worker::StressSampling::Average)];
    fn allowed() -> String {
        "allowed: \"last\" (the stress after the last MD step of a continuum step, the seed's choice), \"average\" (the mean over the continuum step's MD steps)".into()
    }
}

/// `bodies.X.material.precision`: the arithmetic of the MD boxes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MdPrecision {
    Double,
    /// The CUDA back end's mixed precision; the in-process CPU back ends compute in double.
    Mixed,
}

impl SceneName for MdPrecision {
    const FIELD: &'static str = "precision";
    const NAMES: &'static [(&'static str, Self)] = &[("double", MdPrecision::Double), ("mixed", MdPrecision::Mixed)];
    fn allowed() -> String {
        "allowed: \"double\" (the CPU back ends compute in double; \"mixed\" belongs to the CUDA back end)".into()
    }
}

/// `bodies.X.material.deformation`: the engine's [`md_worker::DeformMode`], or `auto` (affine in
/// 1D, seed otherwise; resolved to one of them by validation).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Deformation {
    Auto,
    Affine,
    Seed,
}

impl SceneName for Deformation {
    const FIELD: &'static str = "deformation";
    const NAMES: &'static [(&'static str, Self)] =
        &[("affine", Deformation::Affine), ("seed", Deformation::Seed), ("auto", Deformation::Auto)];
    fn allowed() -> String {
        "allowed: \"seed\" (any dimension), \"affine\" (1D only: it takes diagonal gradients), \"auto\"".into()
    }
}

/// Stress components a direct-MD reference can score (columns `<c>` of the particle files and
/// `<c>_gpa` of the profile).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Component {
    Sxx,
    Syy,
    Szz,
}

impl Component {
    /// The column name (`sxx`).
    pub fn as_str(self) -> &'static str {
        self.scene_name()
    }
}

impl PartialEq<&str> for Component {
    fn eq(&self, other: &&str) -> bool {
        self.as_str() == *other
    }
}

impl fmt::Display for Component {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl SceneName for Component {
    const FIELD: &'static str = "component";
    const NAMES: &'static [(&'static str, Self)] = &[("sxx", Component::Sxx), ("syy", Component::Syy), ("szz", Component::Szz)];
    fn allowed() -> String {
        format!(
            "allowed: {} (sxx: the shock direction of a 1D bar)",
            Self::NAMES.iter().map(|(n, _)| format!("{n:?}")).collect::<Vec<_>>().join(", ")
        )
    }
}

/// A named face condition.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaceName {
    Free,
    Fixed,
    Reflective,
    /// Reflective by another name.
    Roller,
    Periodic,
}

impl SceneName for FaceName {
    /// Faces are plain values of their key (`boundary.x_min`): the error's place names it.
    const FIELD: &'static str = "";
    const NAMES: &'static [(&'static str, Self)] = &[
        ("free", FaceName::Free),
        ("fixed", FaceName::Fixed),
        ("reflective", FaceName::Reflective),
        ("roller", FaceName::Roller),
        ("periodic", FaceName::Periodic),
    ];
    fn allowed() -> String {
        "allowed: \"free\", \"fixed\", \"reflective\", \"roller\", \"periodic\", or { piston = [velocity per axis, m/s] }".into()
    }
}

impl Serialize for FaceName {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        named::serialize(self, s)
    }
}

/// One face's condition: a name, or `{ piston = [vx, ...] }`.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[serde(untagged)]
pub enum FaceSpec {
    Named(FaceName),
    Piston { piston: Vec<f64> },
}

impl Default for FaceSpec {
    fn default() -> Self {
        FaceSpec::Named(FaceName::Free)
    }
}

impl<'de> Deserialize<'de> for FaceSpec {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Face;
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Piston {
            piston: Vec<f64>,
        }
        impl<'de> Visitor<'de> for Face {
            type Value = FaceSpec;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a face name (\"free\", \"fixed\", \"reflective\", \"roller\", \"periodic\") or { piston = [...] }")
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<FaceSpec, E> {
                FaceName::from_scene_name(v).map(FaceSpec::Named).ok_or_else(|| unknown("", v, FaceName::allowed()))
            }
            fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<FaceSpec, A::Error> {
                let p = Piston::deserialize(de::value::MapAccessDeserializer::new(map))?;
                Ok(FaceSpec::Piston { piston: p.piston })
            }
        }
        d.deserialize_any(Face)
    }
}
