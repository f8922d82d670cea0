//! Structured text: YAML, JSON and OpenCV's FileStorage XML as one tree (`serde_json::Value`),
//! and the typed reads (numbers, lists, image sizes) every reader shares; each error names the
//! file and the field.

use std::path::Path;

use serde_json::Value;

use super::{camera_error, format_error};
use crate::error::Result;

/// Parses YAML (a leading OpenCV `%YAML:1.0` line, which is not valid YAML, is skipped; tags
/// such as `!!opencv-matrix` are ignored), JSON (text starting with `{`) or OpenCV FileStorage
/// XML (text starting with `<`, see [`xml_to_json`]) into a JSON tree.
pub(super) fn parse_tree(text: &str, path: &Path) -> Result<Value> {
    let trimmed = text.trim_start_matches('\u{feff}').trim_start();
    if trimmed.starts_with('<') {
        let doc = roxmltree::Document::parse(trimmed)
            .map_err(|e| format_error(path, format!("not valid XML: {e}")))?;
        let root = doc.root_element();
        if root.tag_name().name() != "opencv_storage" {
            return Err(format_error(
                path,
                format!(
                    "an XML file whose root is <{}>, not OpenCV's <opencv_storage>",
                    root.tag_name().name()
                ),
            ));
        }
        return Ok(xml_to_json(root));
    }
    if trimmed.starts_with('{') {
        return serde_json::from_str(trimmed)
            .map_err(|e| format_error(path, format!("not valid JSON: {e}")));
    }
    let body = match trimmed.strip_prefix("%YAML") {
        // Drop the directive line (`%YAML:1.0` or `%YAML 1.x`).
        Some(rest) => rest.split_once('\n').map_or("", |(_, body)| body),
        None => trimmed,
    };
    let docs = yaml_rust2::YamlLoader::load_from_str(body)
        .map_err(|e| format_error(path, format!("not valid YAML: {e}")))?;
    match docs.into_iter().next() {
        Some(doc) => Ok(yaml_to_json(&doc)),
        None => Err(format_error(path, "empty file".to_string())),
    }
}

/// An element of OpenCV FileStorage XML as the tree its YAML would give: an element with
/// child elements is a map (a sequence when every child is `<_>`, FileStorage's list items);
/// a leaf is a number, a list of numbers (whitespace-separated, as in a matrix's `<data>`) or a
/// string (quotes removed). The attribute `type_id` is ignored, like YAML's tags.
fn xml_to_json(node: roxmltree::Node) -> Value {
    let children: Vec<roxmltree::Node> = node.children().filter(|n| n.is_element()).collect();
    if children.is_empty() {
        let text: String = node
            .children()
            .filter(|n| n.is_text())
            .filter_map(|n| n.text())
            .collect();
        let text = text.trim();
        let numbers: Option<Vec<f64>> = text.split_whitespace().map(parse_float).collect();
        return match numbers {
            Some(v) if v.len() == 1 => Value::from(v[0]),
            Some(v) if !v.is_empty() => Value::Array(v.into_iter().map(Value::from).collect()),
            _ => Value::String(text.trim_matches('"').to_string()),
        };
    }
    if children.iter().all(|c| c.tag_name().name() == "_") {
        return Value::Array(children.into_iter().map(xml_to_json).collect());
    }
    Value::Object(
        children
            .into_iter()
            .map(|c| (c.tag_name().name().to_string(), xml_to_json(c)))
            .collect(),
    )
}

pub(super) fn yaml_to_json(y: &yaml_rust2::Yaml) -> Value {
    use yaml_rust2::Yaml;
    match y {
        Yaml::Real(s) => parse_float(s).map_or_else(|| Value::String(s.clone()), Value::from),
        Yaml::Integer(i) => Value::from(*i),
        Yaml::String(s) => Value::String(s.clone()),
        Yaml::Boolean(b) => Value::Bool(*b),
        Yaml::Array(items) => Value::Array(items.iter().map(yaml_to_json).collect()),
        Yaml::Hash(map) => Value::Object(
            map.iter()
                .map(|(k, v)| {
                    let key = match k {
                        Yaml::String(s) | Yaml::Real(s) => s.clone(),
                        Yaml::Integer(i) => i.to_string(),
                        Yaml::Boolean(b) => b.to_string(),
                        _ => String::new(),
                    };
                    (key, yaml_to_json(v))
                })
                .collect(),
        ),
        Yaml::Null | Yaml::Alias(_) | Yaml::BadValue => Value::Null,
    }
}

/// A float as YAML writers print it, including OpenCV's `1.` and `1.e-03`.
pub(super) fn parse_float(s: &str) -> Option<f64> {
    let s = s.trim();
    s.parse::<f64>()
        .ok()
        .or_else(|| s.replace(".e", ".0e").replace(".E", ".0E").parse().ok())
}

/// A number at `field` of `v` (numbers, or strings holding one).
pub(super) fn number(v: &Value, path: &Path, field: &str) -> Result<f64> {
    let x = match v {
        Value::Number(n) => n.as_f64(),
        Value::String(s) => parse_float(s),
        _ => None,
    };
    x.ok_or_else(|| camera_error(path, field, format!("expected a number, found {v}")))
}

pub(super) fn numbers(v: &Value, path: &Path, field: &str) -> Result<Vec<f64>> {
    match v {
        Value::Array(items) => items
            .iter()
            .enumerate()
            .map(|(i, x)| number(x, path, &format!("{field}[{i}]")))
            .collect(),
        other => Err(camera_error(
            path,
            field,
            format!("expected a list of numbers, found {other}"),
        )),
    }
}

pub(super) fn get<'a>(v: &'a Value, key: &str, path: &Path, field: &str) -> Result<&'a Value> {
    v.get(key)
        .ok_or_else(|| camera_error(path, field, "missing".to_string()))
}

/// A non-negative integer image dimension.
pub(super) fn dimension(v: &Value, path: &Path, field: &str) -> Result<usize> {
    let x = number(v, path, field)?;
    if x >= 1.0 && x.fract() == 0.0 && x < 1e9 {
        Ok(x as usize)
    } else {
        Err(camera_error(
            path,
            field,
            format!("expected a positive whole number of pixels, found {x}"),
        ))
    }
}

/// `[w, h]` from a two-element list.
pub(super) fn size_pair(v: &Value, path: &Path, field: &str) -> Result<[usize; 2]> {
    match v {
        Value::Array(items) if items.len() == 2 => Ok([
            dimension(&items[0], path, &format!("{field}[0]"))?,
            dimension(&items[1], path, &format!("{field}[1]"))?,
        ]),
        other => Err(camera_error(
            path,
            field,
            format!("expected [width, height], found {other}"),
        )),
    }
}

pub(super) fn expect_len(
    values: &[f64],
    n: usize,
    path: &Path,
    field: &str,
    what: &str,
) -> Result<()> {
    if values.len() == n {
        Ok(())
    } else {
        Err(camera_error(
            path,
            field,
            format!("{what}: expected {n} values, found {}", values.len()),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opencv_floats_parse() {
        assert_eq!(parse_float("1."), Some(1.0));
        assert_eq!(parse_float("2.8700000000000000e+02"), Some(287.0));
        assert_eq!(parse_float("1.e-03"), Some(1e-3));
        assert_eq!(parse_float("-.5"), Some(-0.5));
        assert_eq!(parse_float("x"), None);
    }
}
