//! The web console, served by `fresa serve` at `/`: plain HTML, CSS and ES modules under
//! `web/`, embedded here at compile time so the binary works offline and building needs no Node
//! toolchain. This crate is only the files; `fresa-http` serves them (content type, ETag, gzip).

/// One embedded file.
#[derive(Debug)]
pub struct Asset {
    /// Path under `/assets/` (`index.html` is served at `/`).
    pub name: &'static str,
    pub content_type: &'static str,
    pub bytes: &'static [u8],
}

macro_rules! assets {
    ($($name:literal => $ctype:literal),* $(,)?) => {
        /// Every file of the console.
        pub static ASSETS: &[Asset] = &[
            $(Asset {
                name: $name,
                content_type: $ctype,
                bytes: include_bytes!(concat!("../web/", $name)),
            }),*
        ];
    };
}

const JS: &str = "text/javascript; charset=utf-8";

assets! {
    "index.html" => "text/html; charset=utf-8",
    "app.css" => "text/css; charset=utf-8",
    "app.js" => "text/javascript; charset=utf-8",
    "api.js" => "text/javascript; charset=utf-8",
    "ui.js" => "text/javascript; charset=utf-8",
    "overview.js" => "text/javascript; charset=utf-8",
    "machine.js" => "text/javascript; charset=utf-8",
    "jobs.js" => "text/javascript; charset=utf-8",
    "toolpath.js" => "text/javascript; charset=utf-8",
    "pendants.js" => "text/javascript; charset=utf-8",
    "events.js" => "text/javascript; charset=utf-8",
    "plugins.js" => "text/javascript; charset=utf-8",
    "holds.js" => "text/javascript; charset=utf-8",
    "heightmap.js" => "text/javascript; charset=utf-8",
    "prefs.js" => "text/javascript; charset=utf-8",
    "runscreen.js" => "text/javascript; charset=utf-8",
    "records.js" => "text/javascript; charset=utf-8",
    "favicon.svg" => "image/svg+xml",
}

/// The file named `name` (e.g. `app.js`), if the console has one.
pub fn find(name: &str) -> Option<&'static Asset> {
    ASSETS.iter().find(|a| a.name == name)
}

/// Whether a content type is JavaScript (the module loader insists on it).
pub fn is_script(a: &Asset) -> bool {
    a.content_type == JS
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_module_import_names_an_embedded_file() {
        for a in ASSETS.iter().filter(|a| is_script(a)) {
            let text = std::str::from_utf8(a.bytes).unwrap_or("");
            for line in text.lines().filter(|l| l.starts_with("import ")) {
                let Some(spec) = line.split(['\'', '"']).nth(1) else {
                    continue;
                };
                let name = spec.trim_start_matches("./");
                assert!(
                    find(name).is_some(),
                    "{}: imports {spec}, not embedded",
                    a.name
                );
            }
        }
    }

    #[test]
    fn the_page_loads_the_app_module() {
        let index = find("index.html").map(|a| a.bytes).unwrap_or_default();
        let index = std::str::from_utf8(index).unwrap_or("");
        assert!(index.contains("src=\"/assets/app.js\""));
    }
}
