//! Merging the file, environment and override layers, and parsing the result into typed structs.

use crate::error::{ConfigError, Result};
use serde::de::DeserializeOwned;
use std::path::{Path, PathBuf};

/// Environment variables `UMGEN__A__B=v` set key `a.b`.
pub const ENV_PREFIX: &str = "UMGEN";
const SEP: &str = "__";

/// The merged layers of a configuration, before they are given a type.
#[derive(Debug, Clone)]
pub struct RawConfig {
    path: PathBuf,
    table: toml::Table,
    overrides: Vec<(String, String)>,
    env: Vec<(String, String)>,
}

impl RawConfig {
    /// Merges `path`, the process environment and `overrides` (`key=value` strings).
    pub fn load(path: &Path, overrides: &[String]) -> Result<Self> {
        Self::load_with_env(path, std::env::vars(), overrides)
    }

    /// As [`RawConfig::load`], with the environment given explicitly (tests, embedding).
    pub fn load_with_env(
        path: &Path,
        env: impl IntoIterator<Item = (String, String)>,
        overrides: &[String],
    ) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|error| ConfigError::Io {
            path: path.into(),
            error,
        })?;
        // Parse once ourselves: toml's messages carry line and column, the merge layer's do not.
        toml::from_str::<toml::Table>(&text).map_err(|e| ConfigError::Syntax {
            path: path.into(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let mut env_vars = config::Map::new();
        let mut env_keys = Vec::new();
        for (var, value) in env {
            if let Some(key) = env_key(&var) {
                env_keys.push((key, var.clone()));
                env_vars.insert(var, value);
            }
        }
        let mut builder = config::Config::builder()
            .add_source(config::File::from_str(&text, config::FileFormat::Toml))
            .add_source(
                config::Environment::with_prefix(ENV_PREFIX)
                    .prefix_separator(SEP)
                    .separator(SEP)
                    .try_parsing(true)
                    .source(Some(env_vars)),
            );
        let mut parsed = Vec::with_capacity(overrides.len());
        for arg in overrides {
            let (key, value) = parse_override(arg)?;
            builder = builder
                .set_override(key.as_str(), value)
                .map_err(|e| ConfigError::Override {
                    arg: arg.clone(),
                    message: e.to_string(),
                })?;
            parsed.push((key, arg.clone()));
        }
        let merge = |e: config::ConfigError| ConfigError::Merge {
            path: path.into(),
            message: e.to_string(),
        };
        let table: toml::Table = builder.build().map_err(merge)?.try_deserialize().map_err(merge)?;
        Ok(Self {
            path: path.into(),
            table,
            overrides: parsed,
            env: env_keys,
        })
    }

    /// The file the base layer came from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The merged table.
    pub fn table(&self) -> &toml::Table {
        &self.table
    }

    /// The whole configuration as a typed struct; errors name the key path and its layer.
    pub fn parse<T: DeserializeOwned>(&self) -> Result<T> {
        self.parse_value(String::new(), toml::Value::Table(self.table.clone()))
    }

    /// One section (a dotted key path) as a typed struct; a missing section parses from an empty table.
    pub fn section<T: DeserializeOwned>(&self, key: &str) -> Result<T> {
        let mut value = toml::Value::Table(self.table.clone());
        for part in key.split('.') {
            value = match value {
                toml::Value::Table(mut t) => t.remove(part).unwrap_or(toml::Value::Table(toml::Table::new())),
                other => {
                    return Err(self.key_error(key, format!("expected a table, found {}", other.type_str())));
                }
            };
        }
        self.parse_value(key.to_string(), value)
    }

    fn parse_value<T: DeserializeOwned>(&self, prefix: String, value: toml::Value) -> Result<T> {
        serde_path_to_error::deserialize(value).map_err(|e| {
            let path = e.path().to_string();
            let key = match (prefix.is_empty(), path == ".") {
                (true, _) => path,
                (false, true) => prefix,
                (false, false) => format!("{prefix}.{path}"),
            };
            self.key_error(
                &key,
                e.into_inner()
                    .to_string()
                    .lines()
                    .next()
                    .unwrap_or_default()
                    .to_string(),
            )
        })
    }

    fn key_error(&self, key: &str, message: String) -> ConfigError {
        ConfigError::Key {
            key: key.into(),
            origin: self.origin(key),
            message,
        }
    }

    /// Which layer set `key` (or the table holding it): a `--set` override, an environment variable, or
    /// the file.
    pub fn origin(&self, key: &str) -> String {
        let related =
            |k: &str| k == key || key.starts_with(&format!("{k}.")) || k.starts_with(&format!("{key}."));
        if let Some((_, arg)) = self.overrides.iter().rev().find(|(k, _)| related(k)) {
            return format!("from --set {arg}");
        }
        if let Some((_, var)) = self.env.iter().find(|(k, _)| related(k)) {
            return format!("from environment variable {var}");
        }
        format!("in {}", self.path.display())
    }
}

/// `UMGEN__TRAIN__STEPS` → `train.steps`; `None` for other variables.
fn env_key(var: &str) -> Option<String> {
    let rest = var.strip_prefix(ENV_PREFIX)?.strip_prefix(SEP)?;
    (!rest.is_empty()).then(|| {
        rest.split(SEP)
            .map(str::to_lowercase)
            .collect::<Vec<_>>()
            .join(".")
    })
}

/// `train.steps=60` → (`train.steps`, 60). The value is a TOML value when it parses as one, else a string.
fn parse_override(arg: &str) -> Result<(String, config::Value)> {
    let fail = |message: &str| ConfigError::Override {
        arg: arg.into(),
        message: message.into(),
    };
    let (key, value) = arg
        .split_once('=')
        .ok_or_else(|| fail("expected key=value, e.g. train.steps=60"))?;
    let key = key.trim();
    let word_ok = |p: &str| {
        !p.is_empty()
            && p.chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    };
    if !key.split('.').all(word_ok) {
        return Err(fail("the key must be dotted words, e.g. train.steps"));
    }
    let value = value.trim();
    let parsed = toml::from_str::<toml::Table>(&format!("v = {value}"))
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(value.to_string()));
    Ok((key.to_string(), to_config_value(parsed)))
}

fn to_config_value(v: toml::Value) -> config::Value {
    use config::ValueKind as K;
    let kind = match v {
        toml::Value::String(s) => K::String(s),
        toml::Value::Integer(i) => K::I64(i),
        toml::Value::Float(f) => K::Float(f),
        toml::Value::Boolean(b) => K::Boolean(b),
        toml::Value::Datetime(d) => K::String(d.to_string()),
        toml::Value::Array(a) => K::Array(a.into_iter().map(to_config_value).collect()),
        toml::Value::Table(t) => K::Table(t.into_iter().map(|(k, v)| (k, to_config_value(v))).collect()),
    };
    config::Value::new(None, kind)
}
