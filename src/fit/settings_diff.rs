//! The differences between two settings records (any serialisable settings, compared as JSON),
//! each named by its dotted path with the old and the new value: what a refusal to resume a run
//! prints, so the user sees which flag changed instead of "other settings".

use serde_json::Value;

/// One differing setting: its dotted path (`training.fit.lr_material`, `prior.labelled_views`),
/// the recorded value and the current one (JSON text; `absent` when one side lacks it).
#[derive(Clone, Debug, PartialEq)]
pub struct Difference {
    pub path: String,
    pub old: String,
    pub new: String,
}

impl std::fmt::Display for Difference {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {} → {}", self.path, self.old, self.new)
    }
}

fn text(v: Option<&Value>) -> String {
    v.map_or_else(|| "absent".to_string(), |v| v.to_string())
}

fn walk(path: &str, old: Option<&Value>, new: Option<&Value>, out: &mut Vec<Difference>) {
    let join = |k: &str| if path.is_empty() { k.to_string() } else { format!("{path}.{k}") };
    match (old, new) {
        (Some(Value::Object(a)), Some(Value::Object(b))) => {
            let mut keys: Vec<&String> = a.keys().collect();
            keys.extend(b.keys().filter(|k| !a.contains_key(*k)));
            for k in keys {
                walk(&join(k), a.get(k), b.get(k), out);
            }
        }
        (Some(Value::Array(a)), Some(Value::Array(b))) if a.len() == b.len() => {
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                walk(&join(&i.to_string()), Some(x), Some(y), out);
            }
        }
        (a, b) if a != b => out.push(Difference { path: path.to_string(), old: text(a), new: text(b) }),
        _ => {}
    }
}

/// Every leaf of `old` and `new` that differs (keys in alphabetical order, those only in `new` last).
pub fn differences(old: &Value, new: &Value) -> Vec<Difference> {
    let mut out = Vec::new();
    walk("", Some(old), Some(new), &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn names_each_differing_leaf_with_both_values() {
        let old = json!({"prior": {"source": "none", "labelled_views": 100}, "seed": 0, "effects": [true, 1], "gone": 1});
        let new = json!({"prior": {"source": "none", "labelled_views": 10}, "seed": 0, "effects": [false, 1], "added": "x"});
        let d: Vec<String> = differences(&old, &new).iter().map(|d| d.to_string()).collect();
        assert_eq!(d, ["effects.0: true → false", "gone: 1 → absent", "prior.labelled_views: 100 → 10", "added: absent → \"x\""]);
        assert!(differences(&old, &old).is_empty());
        // Arrays of other lengths differ as a whole.
        assert_eq!(differences(&json!({"a": [1]}), &json!({"a": [1, 2]}))[0].to_string(), "a: [1] → [1,2]");
    }
}
