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

/// A shared library in a plugin directory that was not loaded, and why not.
#[derive(Debug, Clone, Serialize)]
pub struct PluginSkipped {
    pub path: PathBuf,
    pub reason: String,
}

#[derive(Default)]
pub struct Registry {
    libraries: BTreeMap<String, PluginLibrary>,
    /// Files named like plugins that failed to load (bad ABI, missing symbol, ...).
    pub failures: Vec<PluginLoadFailure>,
    /// Other libraries in the plugin directories, not loaded: wrong name, or shadowed.
    pub skipped: Vec<PluginSkipped>,
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
    name.starts_with(&plugin_prefix()) && name.ends_with(std::env::consts::DLL_SUFFIX)
}

fn plugin_prefix() -> String {
    format!("{}fresa_", std::env::consts::DLL_PREFIX)
}

/// Any shared library, plugin or not (so the ones we skip can be listed).
fn is_library(path: &Path) -> bool {
    path.is_file()
        && path
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.ends_with(std::env::consts::DLL_SUFFIX))
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
                .filter(|p| is_library(p))
                .collect();
            files.sort();
            for path in files {
                if !looks_like_plugin(&path) {
                    tracing::info!(path = %path.display(), "library skipped: not named like a plugin");
                    reg.skipped.push(PluginSkipped {
                        reason: format!(
                            "not named like a plugin: plugin files are {}<name>{}",
                            plugin_prefix(),
                            std::env::consts::DLL_SUFFIX
                        ),
                        path,
                    });
                    continue;
                }
                match PluginLibrary::load(&path) {
                    Ok(lib) => {
                        if let Some(first) = reg.libraries.get(lib.name()) {
                            tracing::info!(path = %path.display(), name = lib.name(), "plugin shadowed by an earlier directory");
                            reg.skipped.push(PluginSkipped {
                                reason: format!(
                                    "plugin {:?} is already loaded from {} (an earlier directory wins)",
                                    lib.name(),
                                    first.path().display()
                                ),
                                path: path.clone(),
                            });
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
