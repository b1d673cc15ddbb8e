//! Strict JSON reading: serde ignores fields it does not know, so a misspelt key in a
//! hand-edited file would silently fall back to a default. These helpers find them.

use serde::Serialize;
use serde_json::Value;

/// The top-level keys of `input` that are not in `known`.
pub fn unknown_keys<'a>(input: &'a Value, known: &[String]) -> Vec<&'a str> {
    match input {
        Value::Object(map) => map.keys().filter(|k| !known.iter().any(|n| n == *k)).map(String::as_str).collect(),
        _ => Vec::new(),
    }
}

/// The top-level keys of `v` serialised to JSON (a struct's field names, with its flattened
/// parts).
pub fn keys_of<T: Serialize>(v: &T) -> Vec<String> {
    match serde_json::to_value(v) {
        Ok(Value::Object(map)) => map.keys().cloned().collect(),
        _ => Vec::new(),
    }
}

/// Refuse `input` if it has a top-level key that is not in `known`: the message names the
/// first unknown key and lists the known ones.
pub fn reject_unknown_keys(input: &Value, known: &[String]) -> Result<(), String> {
    match unknown_keys(input, known).first() {
        None => Ok(()),
        Some(k) => {
            let mut names: Vec<&str> = known.iter().map(String::as_str).collect();
            names.sort_unstable();
            Err(format!("unknown field {k:?}, expected one of {}", names.join(", ")))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Serialize)]
    struct S {
        a: u32,
        b: Option<u32>,
    }

    #[test]
    fn finds_misspelt_keys_and_accepts_known_ones() {
        let known = keys_of(&S { a: 1, b: None });
        assert_eq!(known, vec!["a".to_string(), "b".to_string()]);
        let ok: Value = serde_json::from_str(r#"{"a": 1, "b": 2}"#).unwrap();
        assert!(reject_unknown_keys(&ok, &known).is_ok());
        let bad: Value = serde_json::from_str(r#"{"a": 1, "bb": 2}"#).unwrap();
        let e = reject_unknown_keys(&bad, &known).unwrap_err();
        assert!(e.contains("\"bb\"") && e.contains("a, b"), "{e}");
    }
}
