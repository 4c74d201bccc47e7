//! Checks that the Rust structs of `patchwalk_msgs` match the `.msg`/`.srv` files field by field:
//! names, order and types, recursively through nested messages (the CDR wire format is positional, so
//! a mismatch would otherwise only show as wrong values on the wire).
//!
//! The Rust side is read through serde: a recording `Deserializer` walks each type exactly as the CDR
//! deserializer would (`deserialize_struct` with the declared field names in order, `deserialize_f64`,
//! `deserialize_seq`, `deserialize_tuple(N)` for fixed arrays, ...) and builds a type tree. The file side
//! is parsed with a small ROS 2 IDL (.msg) parser. Standard types referenced by our files are checked
//! against their Jazzy definitions, included below.

// An integration test: a failed expectation is a failed test.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]

use std::collections::HashMap;
use std::path::PathBuf;

use serde::de::{self, DeserializeOwned, DeserializeSeed, Visitor};

use patchwalk_msgs::{action, msg, srv};

// ---------------------------------------------------------------------------------------------------
// Type tree shared by both sides.

#[derive(Debug, Clone, PartialEq)]
enum Ty {
    Bool,
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F32,
    F64,
    Str,
    /// Unbounded or bounded sequence (same CDR encoding).
    Seq(Box<Ty>),
    /// Fixed-size array `T[N]`.
    Array(usize, Box<Ty>),
    Struct(Vec<(String, Ty)>),
}

// ---------------------------------------------------------------------------------------------------
// Rust side: a Deserializer that records what it is asked for.

#[derive(Debug)]
struct SchemaError(String);
impl std::fmt::Display for SchemaError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}
impl std::error::Error for SchemaError {}
impl de::Error for SchemaError {
    fn custom<T: std::fmt::Display>(msg: T) -> Self {
        SchemaError(msg.to_string())
    }
}

struct Recorder<'a> {
    out: &'a mut Option<Ty>,
}

/// Feeds `n` recorded elements; `types` receives the type of each.
struct Elements<'a> {
    left: usize,
    types: &'a mut Vec<Ty>,
}

impl<'de> de::SeqAccess<'de> for Elements<'_> {
    type Error = SchemaError;
    fn next_element_seed<T: DeserializeSeed<'de>>(&mut self, seed: T) -> Result<Option<T::Value>, SchemaError> {
        if self.left == 0 {
            return Ok(None);
        }
        self.left -= 1;
        let mut ty = None;
        let value = seed.deserialize(Recorder { out: &mut ty })?;
        self.types.push(ty.ok_or_else(|| SchemaError("element recorded no type".into()))?);
        Ok(Some(value))
    }
}

macro_rules! primitive {
    ($method:ident, $visit:ident, $ty:expr, $value:expr) => {
        fn $method<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, SchemaError> {
            *self.out = Some($ty);
            visitor.$visit($value)
        }
    };
}

impl<'de> de::Deserializer<'de> for Recorder<'_> {
    type Error = SchemaError;

    primitive!(deserialize_bool, visit_bool, Ty::Bool, false);
    primitive!(deserialize_u8, visit_u8, Ty::U8, 0);
    primitive!(deserialize_i8, visit_i8, Ty::I8, 0);
    primitive!(deserialize_u16, visit_u16, Ty::U16, 0);
    primitive!(deserialize_i16, visit_i16, Ty::I16, 0);
    primitive!(deserialize_u32, visit_u32, Ty::U32, 0);
    primitive!(deserialize_i32, visit_i32, Ty::I32, 0);
    primitive!(deserialize_u64, visit_u64, Ty::U64, 0);
    primitive!(deserialize_i64, visit_i64, Ty::I64, 0);
    primitive!(deserialize_f32, visit_f32, Ty::F32, 0.0);
    primitive!(deserialize_f64, visit_f64, Ty::F64, 0.0);
    primitive!(deserialize_string, visit_string, Ty::Str, String::new());
    primitive!(deserialize_str, visit_string, Ty::Str, String::new());

    fn deserialize_seq<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, SchemaError> {
        let mut types = Vec::new();
        let value = visitor.visit_seq(Elements { left: 1, types: &mut types })?;
        let elem = types.pop().ok_or_else(|| SchemaError("sequence recorded no element".into()))?;
        *self.out = Some(Ty::Seq(Box::new(elem)));
        Ok(value)
    }

    fn deserialize_tuple<V: Visitor<'de>>(self, len: usize, visitor: V) -> Result<V::Value, SchemaError> {
        let mut types = Vec::new();
        let value = visitor.visit_seq(Elements { left: len, types: &mut types })?;
        let first = types.first().cloned().ok_or_else(|| SchemaError("empty array".into()))?;
        if types.iter().any(|t| *t != first) {
            return Err(SchemaError("array with mixed element types".into()));
        }
        *self.out = Some(Ty::Array(len, Box::new(first)));
        Ok(value)
    }

    fn deserialize_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        fields: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, SchemaError> {
        let mut types = Vec::new();
        let value = visitor.visit_seq(Elements { left: fields.len(), types: &mut types })?;
        let named = fields.iter().map(|f| f.to_string()).zip(types).collect();
        *self.out = Some(Ty::Struct(named));
        Ok(value)
    }

    fn deserialize_any<V: Visitor<'de>>(self, _visitor: V) -> Result<V::Value, SchemaError> {
        Err(SchemaError("self-describing type: not representable in CDR".into()))
    }

    serde::forward_to_deserialize_any! {
        i128 u128 char bytes byte_buf option unit unit_struct newtype_struct
        tuple_struct map enum identifier ignored_any
    }
}

fn rust_schema<T: DeserializeOwned>() -> Ty {
    let mut ty = None;
    let result = T::deserialize(Recorder { out: &mut ty });
    if let Err(e) = result {
        panic!("cannot record the schema of {}: {e}", std::any::type_name::<T>());
    }
    ty.unwrap_or_else(|| panic!("{} recorded nothing", std::any::type_name::<T>()))
}

// ---------------------------------------------------------------------------------------------------
// File side: a parser of the .msg format (fields and constants; comments; bounded strings/sequences).

/// Jazzy definitions of the standard types our interfaces embed (from ros2/common_interfaces and
/// ros2/rcl_interfaces, comments dropped).
const STANDARD: &[(&str, &str)] = &[
    ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n"),
    ("std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id\n"),
    ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n"),
    ("geometry_msgs/Quaternion", "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"),
    ("geometry_msgs/Pose", "Point position\nQuaternion orientation\n"),
];

fn package_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

struct Definitions {
    texts: HashMap<String, String>,
}

impl Definitions {
    fn load() -> Definitions {
        let mut texts: HashMap<String, String> = STANDARD.iter().map(|(name, text)| (name.to_string(), text.to_string())).collect();
        let dir = package_dir().join("msg");
        for entry in std::fs::read_dir(&dir).expect("msg/ exists") {
            let path = entry.expect("readable msg/ entry").path();
            if path.extension().and_then(|e| e.to_str()) == Some("msg") {
                let stem = path.file_stem().and_then(|s| s.to_str()).expect("utf-8 file name").to_string();
                let text = std::fs::read_to_string(&path).expect("readable .msg");
                texts.insert(format!("patchwalk_msgs/{stem}"), text);
            }
        }
        Definitions { texts }
    }

    /// Type tree of the message `package/Name`.
    fn message(&self, full_name: &str) -> Ty {
        let text = self.texts.get(full_name).unwrap_or_else(|| panic!("no definition of {full_name}"));
        let package = full_name.split('/').next().unwrap_or_default();
        self.fields(text, package, full_name)
    }

    /// Type tree of a field list (a .msg file or one half of a .srv file) of package `package`.
    fn fields(&self, text: &str, package: &str, context: &str) -> Ty {
        let mut fields = Vec::new();
        for raw_line in text.lines() {
            let line = raw_line.split('#').next().unwrap_or_default().trim();
            if line.is_empty() {
                continue;
            }
            let mut words = line.split_whitespace();
            let ty = words.next().unwrap_or_default();
            let rest: String = words.collect::<Vec<_>>().join(" ");
            // Constants: `type NAME=value` (the name is upper case; a field default has a space instead).
            if let Some((name, _)) = rest.split_once('=') {
                let name = name.trim();
                assert!(
                    name.chars().all(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_'),
                    "{context}: constant {name} must be upper case"
                );
                continue;
            }
            let name = rest.split_whitespace().next().unwrap_or_else(|| panic!("{context}: no field name in {line:?}"));
            assert!(
                name.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_'),
                "{context}: field name {name} must be snake_case"
            );
            fields.push((name.to_string(), self.field_type(ty, package, context)));
        }
        if fields.is_empty() {
            // rosidl adds this member to empty structures; it is on the wire.
            fields.push(("structure_needs_at_least_one_member".to_string(), Ty::U8));
        }
        Ty::Struct(fields)
    }

    fn field_type(&self, ty: &str, package: &str, context: &str) -> Ty {
        if let Some(open) = ty.find('[') {
            let base = self.field_type(&ty[..open], package, context);
            let bound = ty[open + 1..].trim_end_matches(']');
            return if bound.is_empty() || bound.starts_with("<=") {
                Ty::Seq(Box::new(base))
            } else {
                let n: usize = bound.parse().unwrap_or_else(|_| panic!("{context}: bad array size in {ty}"));
                Ty::Array(n, Box::new(base))
            };
        }
        match ty {
            "bool" => Ty::Bool,
            "byte" | "uint8" | "char" => Ty::U8,
            "int8" => Ty::I8,
            "uint16" => Ty::U16,
            "int16" => Ty::I16,
            "uint32" => Ty::U32,
            "int32" => Ty::I32,
            "uint64" => Ty::U64,
            "int64" => Ty::I64,
            "float32" => Ty::F32,
            "float64" => Ty::F64,
            t if t == "string" || t.starts_with("string<=") => Ty::Str,
            t if t.contains('/') => self.message(t),
            t => self.message(&format!("{package}/{t}")),
        }
    }

    /// Request and response type trees of `srv/<name>.srv`.
    fn service(&self, name: &str) -> (Ty, Ty) {
        let path = package_dir().join("srv").join(format!("{name}.srv"));
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let mut halves = text.split("\n---");
        let request = halves.next().unwrap_or_default();
        let response = halves.next().unwrap_or_else(|| panic!("{name}.srv has no --- separator"));
        assert!(halves.next().is_none(), "{name}.srv has more than one ---");
        let context = format!("srv/{name}");
        (self.fields(request, "patchwalk_msgs", &context), self.fields(response, "patchwalk_msgs", &context))
    }

    /// Goal, result and feedback type trees of `action/<name>.action`.
    fn action(&self, name: &str) -> (Ty, Ty, Ty) {
        let path = package_dir().join("action").join(format!("{name}.action"));
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let parts: Vec<&str> = text.split("\n---").collect();
        assert_eq!(parts.len(), 3, "{name}.action must have exactly two --- separators (goal, result, feedback)");
        let context = format!("action/{name}");
        let part = |i: usize| self.fields(parts[i], "patchwalk_msgs", &context);
        (part(0), part(1), part(2))
    }
}

fn assert_same(context: &str, from_file: &Ty, from_rust: &Ty) {
    match (from_file, from_rust) {
        (Ty::Struct(file_fields), Ty::Struct(rust_fields)) => {
            let file_names: Vec<&str> = file_fields.iter().map(|(n, _)| n.as_str()).collect();
            let rust_names: Vec<&str> = rust_fields.iter().map(|(n, _)| n.as_str()).collect();
            assert_eq!(file_names, rust_names, "{context}: field names/order differ (file vs Rust)");
            for ((name, file_ty), (_, rust_ty)) in file_fields.iter().zip(rust_fields) {
                assert_same(&format!("{context}.{name}"), file_ty, rust_ty);
            }
        }
        _ => assert_eq!(from_file, from_rust, "{context}: type differs (file vs Rust)"),
    }
}

fn check_message<T: DeserializeOwned>(name: &str) {
    let defs = Definitions::load();
    assert_same(name, &defs.message(&format!("patchwalk_msgs/{name}")), &rust_schema::<T>());
}

fn check_service<Req: DeserializeOwned, Resp: DeserializeOwned>(name: &str) {
    let defs = Definitions::load();
    let (request, response) = defs.service(name);
    assert_same(&format!("{name}.request"), &request, &rust_schema::<Req>());
    assert_same(&format!("{name}.response"), &response, &rust_schema::<Resp>());
}

// ---------------------------------------------------------------------------------------------------

#[test]
fn messages_match_their_msg_files() {
    check_message::<msg::Patch>("Patch");
    check_message::<msg::PatchArray>("PatchArray");
    check_message::<msg::MapperStatus>("MapperStatus");
    check_message::<msg::ExecutorStatus>("ExecutorStatus");
    check_message::<msg::MotionSummary>("MotionSummary");
}

#[test]
fn services_match_their_srv_files() {
    check_service::<srv::RecordKeyframeRequest, srv::RecordKeyframeResponse>("RecordKeyframe");
    check_service::<srv::SelectTargetRequest, srv::SelectTargetResponse>("SelectTarget");
    check_service::<srv::SaveMotionRequest, srv::SaveMotionResponse>("SaveMotion");
    check_service::<srv::ListMotionsRequest, srv::ListMotionsResponse>("ListMotions");
    check_service::<srv::DeleteMotionRequest, srv::DeleteMotionResponse>("DeleteMotion");
    check_service::<srv::PlayMotionRequest, srv::PlayMotionResponse>("PlayMotion");
    check_service::<srv::RebootServosRequest, srv::RebootServosResponse>("RebootServos");
}

fn check_action<G: DeserializeOwned, R: DeserializeOwned, F: DeserializeOwned>(name: &str) {
    let defs = Definitions::load();
    let (goal, result, feedback) = defs.action(name);
    assert_same(&format!("{name}.goal"), &goal, &rust_schema::<G>());
    assert_same(&format!("{name}.result"), &result, &rust_schema::<R>());
    assert_same(&format!("{name}.feedback"), &feedback, &rust_schema::<F>());
}

#[test]
fn actions_match_their_action_files() {
    check_action::<action::PlayMotionGoal, action::PlayMotionResult, action::PlayMotionFeedback>("PlayMotion");
}

#[test]
fn every_interface_file_is_checked_and_built() {
    // A new .msg/.srv/.action must be added to CMakeLists.txt and to the three tests above.
    let cmake = std::fs::read_to_string(package_dir().join("CMakeLists.txt")).expect("CMakeLists.txt");
    let this = std::fs::read_to_string(file!())
        .unwrap_or_else(|_| std::fs::read_to_string(package_dir().join("rust/tests/interface_files.rs")).expect("this test file"));
    for dir in ["msg", "srv", "action"] {
        for entry in std::fs::read_dir(package_dir().join(dir)).expect("interface dir") {
            let path = entry.expect("entry").path();
            let file = path.file_name().and_then(|f| f.to_str()).expect("utf-8 name").to_string();
            let stem = path.file_stem().and_then(|s| s.to_str()).expect("utf-8 name").to_string();
            assert!(cmake.contains(&format!("\"{dir}/{file}\"")), "{dir}/{file} missing in CMakeLists.txt");
            assert!(this.contains(&format!("(\"{stem}\")")), "{dir}/{file} is not checked by this test");
        }
    }
}

#[test]
fn constants_match_the_fixed_numbering() {
    // Patch.msg's constants: the same order as the Rust enums and constants everywhere.
    let defs = Definitions::load();
    let text = defs.texts.get("patchwalk_msgs/Patch").expect("Patch.msg");
    let constants: Vec<(String, u8)> = text
        .lines()
        .filter_map(|l| l.split('#').next())
        .filter_map(|l| l.trim().strip_prefix("uint8 "))
        .filter_map(|l| l.split_once('='))
        .map(|(name, value)| (name.trim().to_string(), value.trim().parse().expect("uint8 constant")))
        .collect();
    let expected = [
        ("ELLIPTIC_PARABOLOID", msg::Patch::ELLIPTIC_PARABOLOID),
        ("HYPERBOLIC_PARABOLOID", msg::Patch::HYPERBOLIC_PARABOLOID),
        ("CYLINDRIC_PARABOLOID", msg::Patch::CYLINDRIC_PARABOLOID),
        ("CIRCULAR_PARABOLOID", msg::Patch::CIRCULAR_PARABOLOID),
        ("PLANE", msg::Patch::PLANE),
        ("SPHERE", msg::Patch::SPHERE),
        ("CIRCULAR_CYLINDER", msg::Patch::CIRCULAR_CYLINDER),
        ("ELLIPSE", msg::Patch::ELLIPSE),
        ("CIRCLE", msg::Patch::CIRCLE),
        ("RECTANGLE", msg::Patch::RECTANGLE),
        ("QUADRILATERAL", msg::Patch::QUADRILATERAL),
    ];
    let expected: Vec<(String, u8)> = expected.iter().map(|(n, v)| (n.to_string(), *v)).collect();
    assert_eq!(constants, expected);
    assert_eq!(
        (0..7).collect::<Vec<u8>>(),
        expected[..7].iter().map(|(_, v)| *v).collect::<Vec<_>>(),
        "surface types are numbered 0..6 in Patch.msg order"
    );
}

#[test]
fn recorder_sees_a_field_order_swap() {
    // The check itself must be able to fail: a struct with two fields swapped is rejected.
    #[derive(serde::Deserialize)]
    #[allow(dead_code)]
    struct Swapped {
        b: u32,
        a: f64,
    }
    let defs = Definitions::load();
    let file = defs.fields("float64 a\nuint32 b\n", "patchwalk_msgs", "test");
    let result = std::panic::catch_unwind(|| assert_same("Swapped", &file, &rust_schema::<Swapped>()));
    assert!(result.is_err());
}
