//! A real headless Chromium driven through WebDriver (Debian's `chromium` and `chromium-driver`,
//! via the `fantoccini` client): each [`Browser`] has its own chromedriver on an ephemeral
//! loopback port and a fresh profile. Waiting is by polling a JavaScript condition with a
//! deadline, never by sleeping. A missing package fails the test naming it.

#![allow(clippy::unwrap_used, clippy::expect_used, dead_code)]

use fantoccini::{Client, ClientBuilder, Locator};
use fresa_tests::serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// Where screenshots go: `<target>/console-screenshots/`.
pub fn screenshot_dir() -> PathBuf {
    let dir = fresa_tests::bin_dir()
        .parent()
        .expect("profile dir has a parent")
        .join("console-screenshots");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Starts chromedriver on an ephemeral port: the child and its port, or what it printed (stdout
/// and stderr) and how it ended when it never said the port.
fn start_driver() -> Result<(Child, u16), String> {
    let mut driver = Command::new(CHROMEDRIVER)
        .arg("--port=0")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start chromedriver");
    // Drained on its own thread so chromedriver never blocks on a full pipe; kept (the last
    // 8 KiB) for the message when it fails.
    let stderr = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
    let err_pipe = driver.stderr.take().unwrap();
    let err_text = stderr.clone();
    let err_reader = std::thread::spawn(move || {
        for line in BufReader::new(err_pipe).lines().map_while(Result::ok) {
            let mut t = err_text.lock().unwrap();
            t.push_str(&line);
            t.push('\n');
            if t.len() > 8192 {
                let cut = t.len() - 8192;
                let cut = (cut..t.len()).find(|&i| t.is_char_boundary(i)).unwrap_or(0);
                t.drain(..cut);
            }
        }
    });
    // "ChromeDriver was started successfully on port N."
    let mut out = BufReader::new(driver.stdout.take().unwrap());
    let mut said = String::new();
    let mut line = String::new();
    while out.read_line(&mut line).unwrap_or(0) > 0 {
        if let Some(rest) = line.split("on port ").nth(1) {
            if line.contains("started successfully") {
                if let Ok(port) = rest.trim().trim_end_matches('.').parse::<u16>() {
                    // Keep draining its stdout so it never blocks on a full pipe.
                    std::thread::spawn(move || for _ in out.lines() {});
                    return Ok((driver, port));
                }
            }
        }
        said.push_str(&line);
        line.clear();
    }
    // Its stdout closed: it exited (or is about to); say how, and what it printed.
    let _ = driver.kill();
    let status = driver.wait();
    let _ = err_reader.join();
    let stderr = stderr.lock().unwrap();
    Err(format!(
        "exit {status:?}; stdout: {said:?}; stderr: {:?}",
        stderr.as_str()
    ))
}

fn require(path: &str, package: &str) {
    assert!(
        Path::new(path).is_file(),
        "{path} is missing: the browser tests need Debian's `{package}` package \
         (apt-get install {package}; tests/run installs it)"
    );
}

pub struct Browser {
    rt: tokio::runtime::Runtime,
    client: Option<Client>,
    driver: Child,
    _profile: tempfile::TempDir,
}

impl Browser {
    pub fn start() -> Browser {
        Browser::start_with(&[])
    }

    /// A browser with extra Chromium switches (e.g. `--force-dark-mode`: the system's theme).
    pub fn start_with(extra: &[&str]) -> Browser {
        require(CHROMIUM, "chromium");
        require(CHROMEDRIVER, "chromium-driver");
        // A chromedriver that exits before it says its port is started once more; the panic
        // says what both attempts printed and how they ended.
        let (driver, port) = start_driver().unwrap_or_else(|first| {
            start_driver().unwrap_or_else(|second| {
                panic!(
                    "chromedriver did not say which port it listens on.\n\
                     first attempt: {first}\nsecond attempt: {second}"
                )
            })
        });
        let profile = tempfile::Builder::new()
            .prefix("fresa-chromium-")
            .tempdir()
            .unwrap();
        let mut args: Vec<String> = [
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-dev-shm-usage",
            "--enable-unsafe-swiftshader",
            "--window-size=1280,1000",
        ]
        .iter()
        .map(|a| a.to_string())
        .collect();
        args.push(format!("--user-data-dir={}", profile.path().display()));
        args.extend(extra.iter().map(|a| a.to_string()));
        let caps = json!({
            "goog:chromeOptions": {
                "binary": CHROMIUM,
                "args": args,
            }
        });
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let url = format!("http://127.0.0.1:{port}");
        let client = rt.block_on(async {
            let deadline = Instant::now() + Duration::from_secs(60);
            loop {
                let mut b =
                    ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new());
                b.capabilities(caps.as_object().unwrap().clone());
                match b.connect(&url).await {
                    Ok(c) => break c,
                    Err(e) if Instant::now() < deadline => {
                        let _ = e;
                        tokio::time::sleep(Duration::from_millis(50)).await;
                    }
                    Err(e) => panic!("cannot start a Chromium session through chromedriver: {e}"),
                }
            }
        });
        Browser {
            rt,
            client: Some(client),
            driver,
            _profile: profile,
        }
    }

    fn c(&self) -> &Client {
        self.client.as_ref().unwrap()
    }

    pub fn goto(&self, url: &str) {
        self.rt.block_on(self.c().goto(url)).unwrap();
    }

    /// Runs a script (`return ...;`) and gives its JSON value.
    pub fn js(&self, script: &str) -> Value {
        self.rt
            .block_on(self.c().execute(script, vec![]))
            .unwrap_or_else(|e| panic!("script failed: {e}\n{script}"))
    }

    /// Runs an asynchronous script: it calls `arguments[arguments.length - 1](value)` when done.
    pub fn js_async(&self, script: &str) -> Value {
        self.rt
            .block_on(self.c().execute_async(script, vec![]))
            .unwrap_or_else(|e| panic!("script failed: {e}\n{script}"))
    }

    /// Polls `script` until it returns something truthy; panics after `timeout` naming `what`
    /// and the page's visible text.
    #[track_caller]
    pub fn wait(&self, what: &str, timeout: Duration, script: &str) -> Value {
        let deadline = Instant::now() + timeout;
        loop {
            let v = self.js(script);
            let truthy =
                !matches!(&v, Value::Null | Value::Bool(false)) && v != json!("") && v != json!(0);
            if truthy {
                return v;
            }
            if Instant::now() >= deadline {
                let text = self.js("return document.body.innerText;");
                panic!(
                    "timed out after {timeout:?} waiting for {what}; last value {v}; page:\n{}",
                    text.as_str().unwrap_or("")
                );
            }
            std::thread::sleep(Duration::from_millis(25));
        }
    }

    /// Waits until `css` matches an element and returns its text.
    #[track_caller]
    pub fn wait_text(&self, css: &str, timeout: Duration) -> String {
        let sel = serde_json_str(css);
        self.wait(
            &format!("element {css}"),
            timeout,
            &format!("const e = document.querySelector({sel}); return e ? (e.textContent || ' ') : null;"),
        )
        .as_str()
        .unwrap()
        .to_string()
    }

    /// Clicks the element (a real WebDriver click: it must be visible and enabled).
    #[track_caller]
    pub fn click(&self, css: &str) {
        self.wait_enabled(css, Duration::from_secs(30));
        self.rt.block_on(async {
            let e = self.c().find(Locator::Css(css)).await.unwrap();
            e.click()
                .await
                .unwrap_or_else(|err| panic!("click {css}: {err}"));
        });
    }

    #[track_caller]
    pub fn wait_enabled(&self, css: &str, timeout: Duration) {
        let sel = serde_json_str(css);
        self.wait(
            &format!("{css} to be enabled"),
            timeout,
            &format!("const e = document.querySelector({sel}); return !!e && !e.disabled;"),
        );
    }

    /// Whether the element is disabled (it must exist).
    #[track_caller]
    pub fn disabled(&self, css: &str) -> bool {
        let sel = serde_json_str(css);
        self.wait(
            &format!("element {css}"),
            Duration::from_secs(30),
            &format!("return !!document.querySelector({sel});"),
        );
        self.js(&format!("return document.querySelector({sel}).disabled;"))
            .as_bool()
            .unwrap()
    }

    /// Replaces an input's text as a user would type it, once the page has rendered it enabled
    /// (pages render after their first requests answer, as `click` waits for them too).
    #[track_caller]
    pub fn type_into(&self, css: &str, text: &str) {
        self.wait_enabled(css, Duration::from_secs(30));
        self.rt.block_on(async {
            let e = self.c().find(Locator::Css(css)).await.unwrap();
            e.clear().await.unwrap();
            e.send_keys(text).await.unwrap();
        });
    }

    #[track_caller]
    pub fn select(&self, css: &str, value: &str) {
        self.wait_enabled(css, Duration::from_secs(30));
        self.rt.block_on(async {
            let e = self.c().find(Locator::Css(css)).await.unwrap();
            e.select_by_value(value).await.unwrap();
        });
    }

    /// Chooses a file in an `<input type=file>`, as the file picker does.
    pub fn choose_file(&self, css: &str, file: &Path) {
        let abs = std::fs::canonicalize(file).unwrap();
        self.rt.block_on(async {
            let e = self.c().find(Locator::Css(css)).await.unwrap();
            e.send_keys(abs.to_str().unwrap()).await.unwrap();
        });
    }

    /// Resizes the window (e.g. to a tablet's viewport).
    pub fn resize(&self, width: u32, height: u32) {
        self.rt
            .block_on(self.c().set_window_size(width, height))
            .unwrap();
    }

    /// Resizes the window so that the page's viewport (`innerWidth` x `innerHeight`) is
    /// `width` x `height` CSS pixels, whatever the window's frame takes.
    pub fn viewport(&self, width: u32, height: u32) {
        self.resize(width, height);
        let inner = self.js("return [innerWidth, innerHeight];");
        let (iw, ih) = (
            inner[0].as_i64().unwrap_or(0),
            inner[1].as_i64().unwrap_or(0),
        );
        let (dw, dh) = (width as i64 - iw, height as i64 - ih);
        if dw != 0 || dh != 0 {
            self.resize((width as i64 + dw) as u32, (height as i64 + dh) as u32);
        }
        let inner = self.js("return [innerWidth, innerHeight];");
        assert_eq!(
            inner,
            json!([width, height]),
            "cannot give the page a {width} x {height} viewport"
        );
    }

    /// Reloads the page.
    pub fn reload(&self) {
        self.rt.block_on(self.c().refresh()).unwrap();
    }

    /// Saves a PNG of the viewport under [`screenshot_dir`] and returns its path.
    pub fn screenshot(&self, name: &str) -> PathBuf {
        let png = self.rt.block_on(self.c().screenshot()).unwrap();
        assert!(png.starts_with(b"\x89PNG"), "not a PNG");
        let path = screenshot_dir().join(format!("{name}.png"));
        std::fs::write(&path, png).unwrap();
        path
    }
}

fn serde_json_str(s: &str) -> String {
    Value::String(s.to_string()).to_string()
}

impl Drop for Browser {
    fn drop(&mut self) {
        if let Some(c) = self.client.take() {
            let _ = self.rt.block_on(c.close());
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}
