//! "Did you mean" for misspelt keys and values: serde's "unknown field" / "unknown variant"
//! messages list the valid names; the nearest by edit distance is suggested.

/// Levenshtein distance (insertions, deletions, substitutions) between `a` and `b`, by chars.
pub fn edit_distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.chars().collect();
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    let mut cur = vec![0; b.len() + 1];
    for i in 1..=a.len() {
        cur[0] = i;
        for j in 1..=b.len() {
            let sub = prev[j - 1] + usize::from(a[i - 1] != b[j - 1]);
            cur[j] = sub.min(prev[j] + 1).min(cur[j - 1] + 1);
        }
        std::mem::swap(&mut prev, &mut cur);
    }
    prev[b.len()]
}

/// The candidate nearest to `word`, if it is close enough to be a plausible typo: at most
/// `max(2, len / 3)` edits (case-insensitive), ties to the first.
pub fn nearest<'a>(word: &str, candidates: &[&'a str]) -> Option<&'a str> {
    let w = word.to_lowercase();
    let limit = 2.max(word.chars().count() / 3);
    candidates
        .iter()
        .map(|c| (edit_distance(&w, &c.to_lowercase()), *c))
        .filter(|(d, _)| *d <= limit)
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

/// `; did you mean `B`?` for the candidate `B` nearest `word` (see [`nearest`]), or nothing:
/// the tail of an "unknown name" message.
pub fn did_you_mean(word: &str, candidates: &[&str]) -> String {
    nearest(word, candidates)
        .map(|b| format!("; did you mean `{b}`?"))
        .unwrap_or_default()
}

/// What serde said was unknown, parsed from its message: `(what, name, valid names)`, `what`
/// being `field` or `variant`. Handles "unknown field `x`, expected one of `a`, `b`",
/// "... expected `a` or `b`", "... expected `a`" and "... there are no fields".
pub fn parse_unknown(message: &str) -> Option<(&'static str, String, Vec<String>)> {
    let (what, rest) = if let Some(i) = message.find("unknown field `") {
        ("field", &message[i + "unknown field `".len()..])
    } else if let Some(i) = message.find("unknown variant `") {
        ("variant", &message[i + "unknown variant `".len()..])
    } else {
        return None;
    };
    let end = rest.find('`')?;
    let name = rest[..end].to_string();
    let tail = &rest[end + 1..];
    let tail = tail.lines().next().unwrap_or("");
    let expected: Vec<String> = tail
        .split('`')
        .enumerate()
        .filter(|(i, _)| i % 2 == 1)
        .map(|(_, s)| s.to_string())
        .collect();
    Some((what, name, expected))
}

/// A "did you mean" sentence for a serde message, if it names an unknown field or variant with
/// a close valid name; otherwise the list of valid names, if any.
pub fn hint(message: &str) -> Option<String> {
    let (what, name, expected) = parse_unknown(message)?;
    let cands: Vec<&str> = expected.iter().map(|s| s.as_str()).collect();
    match nearest(&name, &cands) {
        Some(best) => Some(format!("did you mean `{best}` instead of `{name}`?")),
        None if !cands.is_empty() => Some(format!(
            "`{name}` is not a valid {what} here; valid: {}",
            cands.join(", ")
        )),
        None => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distances_and_suggestions() {
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        assert_eq!(edit_distance("", "abc"), 3);
        assert_eq!(edit_distance("lr", "lr"), 0);
        assert_eq!(nearest("learning_rate", &["lr", "eps"]), None);
        assert_eq!(
            nearest("weigth_decay", &["lr", "weight_decay"]),
            Some("weight_decay")
        );
        assert_eq!(
            nearest("calibated", &["standard", "calibrated"]),
            Some("calibrated")
        );
        assert_eq!(nearest("Epochs", &["epochs", "steps"]), Some("epochs"));
    }

    #[test]
    fn serde_messages_are_understood() {
        let m = "unknown field `batchsize`, expected one of `epochs`, `steps`, `batch_size`";
        let (what, name, exp) = parse_unknown(m).unwrap();
        assert_eq!((what, name.as_str()), ("field", "batchsize"));
        assert_eq!(exp, ["epochs", "steps", "batch_size"]);
        assert_eq!(
            hint(m).unwrap(),
            "did you mean `batch_size` instead of `batchsize`?"
        );
        let m = "unknown variant `calibated`, expected `standard` or `calibrated`";
        assert_eq!(
            hint(m).unwrap(),
            "did you mean `calibrated` instead of `calibated`?"
        );
        let m = "unknown field `zzz`, expected `name`";
        assert_eq!(
            hint(m).unwrap(),
            "`zzz` is not a valid field here; valid: name"
        );
        assert!(hint("invalid type: string, expected u64").is_none());
    }
}
