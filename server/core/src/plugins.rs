//! Finds and loads plugin libraries from the plugin search path.

use fresa_plugin_api::host::PluginLibrary;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Serialize)]
pub struct PluginInfo {
    pub name: String,
    pub version: String,
    pub abi: String,
    pub kinds: Vec<&'static str>,
    pub path: PathBuf,
}

#[derive(Debug, Clone, Serialize)]
pub struct PluginLoadFailure {
    pub path: PathBuf,
    pub error: String,
}

#[derive(Default)]
pub struct Registry {
    libraries: BTreeMap<String, PluginLibrary>,
    pub failures: Vec<PluginLoadFailure>,
}

fn kinds(bits: u32) -> Vec<&'static str> {
    let mut v = Vec::new();
    if bits & fresa_plugin_api::abi::KIND_MACHINE_BACKEND != 0 {
        v.push("machine_backend");
    }
    if bits & fresa_plugin_api::abi::KIND_PENDANT_TRANSPORT != 0 {
        v.push("pendant_transport");
    }
    v
}

/// Plugin files follow the platform's library naming with a `fresa_` stem
/// (`libfresa_sim_machine.so`, `fresa_sim_machine.dll`).
fn looks_like_plugin(path: &Path) -> bool {
    let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
        return false;
    };
    let prefix = format!("{}fresa_", std::env::consts::DLL_PREFIX);
    name.starts_with(&prefix) && name.ends_with(std::env::consts::DLL_SUFFIX)
}

impl Registry {
    /// Loads every plugin in `dirs`. The first directory to provide a name wins, so a plugin dir
    /// given on the command line overrides the defaults. Failures are kept for `/api/v1/plugins`.
    pub fn load(dirs: &[PathBuf]) -> Registry {
        let mut reg = Registry::default();
        for dir in dirs {
            let Ok(entries) = std::fs::read_dir(dir) else {
                continue;
            };
            let mut files: Vec<PathBuf> = entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| looks_like_plugin(p))
                .collect();
            files.sort();
            for path in files {
                match PluginLibrary::load(&path) {
                    Ok(lib) => {
                        if reg.libraries.contains_key(lib.name()) {
                            tracing::debug!(path = %path.display(), name = lib.name(), "plugin shadowed by an earlier directory");
                            continue;
                        }
                        tracing::info!(name = lib.name(), version = lib.version(), path = %path.display(), "plugin loaded");
                        reg.libraries.insert(lib.name().to_string(), lib);
                    }
                    Err(e) => {
                        tracing::error!(path = %path.display(), error = %e, "plugin not loaded");
                        reg.failures.push(PluginLoadFailure {
                            path: path.clone(),
                            error: e.to_string(),
                        });
                    }
                }
            }
        }
        reg
    }

    pub fn get(&self, name: &str) -> Option<&PluginLibrary> {
        self.libraries.get(name)
    }

    pub fn names(&self) -> Vec<String> {
        self.libraries.keys().cloned().collect()
    }

    pub fn infos(&self) -> Vec<PluginInfo> {
        self.libraries
            .values()
            .map(|l| PluginInfo {
                name: l.name().to_string(),
                version: l.version().to_string(),
                abi: format!("{}.{}", l.abi_version().0, l.abi_version().1),
                kinds: kinds(l.kinds()),
                path: l.path().to_path_buf(),
            })
            .collect()
    }
}
