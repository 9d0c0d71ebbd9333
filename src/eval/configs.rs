//! Which configurations a run evaluates: presets, files, union signature specifications.

use super::*;

/// Resolves `--config`.
pub fn load_configs(spec: Option<&str>) -> Result<Vec<Config>> {
    let presets = || {
        let mut v = presets::paper_configs();
        let d = presets::default_config();
        if !v.iter().any(|c| c.name == d.name) {
            v.push(d);
        }
        v
    };
    let Some(spec) = spec else {
        return Ok(presets());
    };
    let path = Path::new(spec);
    if path.is_file() {
        let text = std::fs::read_to_string(path)?;
        let is_toml = path.extension().and_then(|e| e.to_str()) == Some("toml");
        let v: Value = if is_toml {
            let t: toml::Value = toml::from_str(&text)
                .map_err(|e| Error::InvalidArgument(format!("config {spec}: {e}")))?;
            serde_json::to_value(t)
                .map_err(|e| Error::InvalidArgument(format!("config {spec}: {e}")))?
        } else {
            serde_json::from_str(&text)
                .map_err(|e| Error::InvalidArgument(format!("config {spec}: {e}")))?
        };
        let items = match v {
            Value::Array(a) => a,
            Value::Object(ref o) if o.contains_key("configs") => match &o["configs"] {
                Value::Array(a) => a.clone(),
                _ => {
                    return Err(Error::InvalidArgument(format!(
                        "config {spec}: 'configs' must be a list"
                    )))
                }
            },
            other => vec![other],
        };
        let mut out = Vec::new();
        for (i, item) in items.into_iter().enumerate() {
            out.push(
                config_from_value(item).map_err(|e| {
                    Error::InvalidArgument(format!("config {spec}, entry {i}: {e}"))
                })?,
            );
        }
        if out.is_empty() {
            return Err(Error::InvalidArgument(format!(
                "config {spec}: no configuration"
            )));
        }
        return Ok(out);
    }
    match spec {
        "all" => Ok(presets()),
        "paper" => Ok(presets::paper_configs()),
        "default" => Ok(vec![presets::default_config()]),
        names => {
            let all = presets();
            names
                .split(',')
                .map(|n| n.trim())
                .filter(|n| !n.is_empty())
                .map(|n| {
                    all.iter().find(|c| c.name == n).cloned().ok_or_else(|| {
                        Error::InvalidArgument(format!(
                            "--config {n}: not a file, a preset (paper, default, all) or a configuration name; closest: {}",
                            presets::closest_names(n, 5).join(", ")
                        ))
                    })
                })
                .collect()
        }
    }
}

/// One configuration of a `--config` file. A field this version does not know is an error
/// naming its path (`signature.cut_handles.max_neck_aspekt`), not silently dropped: a misspelt
/// or newer option would otherwise evaluate the configuration without it, with nothing to
/// show for it. (The stored specifications of an index are read leniently elsewhere, so that an
/// option removed from the code does not make an index unreadable.)
fn config_from_value(item: Value) -> std::result::Result<Config, String> {
    let mut unknown = Vec::new();
    let c: Config = serde_ignored::deserialize(item, |path| unknown.push(field_path(&path)))
        .map_err(|e| e.to_string())?;
    match unknown.as_slice() {
        [] => Ok(c),
        paths => Err(format!(
            "unknown field{} {}: not an option of this version of shapeseek (check the \
             spelling; the `SignatureSpec` and `QuerySpec` schemas of api/openapi.yaml list the options)",
            if paths.len() > 1 { "s" } else { "" },
            paths
                .iter()
                .map(|p| format!("`{p}`"))
                .collect::<Vec<_>>()
                .join(", ")
        )),
    }
}

/// `signature.cut_handles.max_neck_aspekt`: the JSON keys and list indices of an ignored
/// field, without serde_ignored's `?` for the `Option`s and newtypes it passes through.
fn field_path(path: &serde_ignored::Path) -> String {
    use serde_ignored::Path;
    let mut parts = Vec::new();
    let mut p = path;
    loop {
        p = match p {
            Path::Root => break,
            Path::Seq { parent, index } => {
                parts.push(index.to_string());
                parent
            }
            Path::Map { parent, key } => {
                parts.push(key.clone());
                parent
            }
            Path::Some { parent }
            | Path::NewtypeStruct { parent }
            | Path::NewtypeVariant { parent } => parent,
        };
    }
    parts.reverse();
    parts.join(".")
}

/// Groups of configurations sharing one signature specification: the union of their channels,
/// for specifications that are equal apart from the channel list.
pub fn union_specs(configs: &[Config]) -> (Vec<SignatureSpec>, Vec<usize>) {
    let mut specs: Vec<SignatureSpec> = Vec::new();
    let mut bases: Vec<Value> = Vec::new();
    let mut group_of = Vec::with_capacity(configs.len());
    for c in configs {
        let mut base = c.signature.clone();
        base.channels.clear();
        let bv = serde_json::to_value(&base).unwrap_or(Value::Null);
        let g = match bases.iter().position(|b| *b == bv && bv != Value::Null) {
            Some(g) => g,
            None => {
                bases.push(bv);
                specs.push(base);
                specs.len() - 1
            }
        };
        // Channels are identified by name (as queries refer to them).
        for ch in &c.signature.channels {
            let name = ch.name();
            if !specs[g].channels.iter().any(|x| x.name() == name) {
                specs[g].channels.push(ch.clone());
            }
        }
        group_of.push(g);
    }
    (specs, group_of)
}

/// Does a signature computed for `big` hold every channel of `small`, computed the same way?
pub fn covers(big: &SignatureSpec, small: &SignatureSpec) -> bool {
    let base = |s: &SignatureSpec| {
        let mut b = s.clone();
        b.channels.clear();
        serde_json::to_value(&b).ok()
    };
    base(big).is_some()
        && base(big) == base(small)
        && small
            .channels
            .iter()
            .all(|c| big.channels.iter().any(|x| x == c))
}

/// The name of a preset configuration that is the same method as `cfg` under another name:
/// same query, same specifications of the queried channels, same discretisation (other channels
/// of a shared family specification do not matter). Used for reference look-ups.
pub fn alias_of(cfg: &Config) -> Option<String> {
    let method = |c: &Config| {
        let chans: Vec<Option<&crate::signature::ChannelSpec>> = c
            .query
            .channels
            .iter()
            .map(|n| c.signature.channels.iter().find(|x| &x.name() == n))
            .collect();
        let mut base = c.signature.clone();
        base.channels.clear();
        (
            serde_json::to_value(&c.query).ok(),
            serde_json::to_value(&chans).ok(),
            serde_json::to_value(&base).ok(),
            serde_json::to_value(&c.rerank).ok(),
        )
    };
    let me = method(cfg);
    presets::paper_configs()
        .into_iter()
        .find(|c| c.name != cfg.name && method(c) == me)
        .map(|c| c.name)
}

/// The run's configurations (`--config`, plus the `--loco-fixed` ones it lacks, the window of
/// `--window-percentile` applied), validated against `--k`; and how many of them are
/// candidates of the leave-one-class-out protocol (the first ones).
pub(super) fn run_configs(args: &EvalOptions) -> Result<(Vec<Config>, usize)> {
    let mut configs = load_configs(args.config.as_deref())?;
    // LOCO: the configurations asked for are the candidates; fixed ones are added if missing.
    let n_candidates = configs.len();
    if let Some(lo) = &args.loco {
        for name in &lo.fixed {
            if !configs.iter().any(|c| &c.name == name) {
                configs.extend(load_configs(Some(name))?);
            }
        }
    }
    if let Some(p) = args.window_percentile {
        for c in &mut configs {
            c.calibration.percentile = p;
        }
    }
    for c in &configs {
        c.calibration.validate().map_err(|e| {
            Error::InvalidArgument(format!("configuration {}: calibration: {e}", c.name))
        })?;
        c.query
            .validate()
            .map_err(|e| Error::InvalidArgument(format!("configuration {}: query: {e}", c.name)))?;
        let need = c.signature.min_eigenpairs();
        if args.k < need {
            return Err(Error::InvalidArgument(format!(
                "configuration {} needs at least {need} eigenpairs (its ShapeDNA channel), \
                 --k is {}",
                c.name, args.k
            )));
        }
    }
    Ok((configs, n_candidates))
}
