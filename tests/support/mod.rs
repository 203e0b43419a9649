//! What the server tests share: a real `worldpack serve` on loopback, HTTP
//! with timeouts, temporary stores and a PostgreSQL cluster of their own.
#![allow(dead_code)] // each test binary uses its own part of this

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::LazyLock;
use std::time::Duration;

use serde_json::{Value, json};
use std::io::Read;

/// Every request of these tests: a server or Triton that stops answering
/// fails its test within minutes instead of hanging the whole run.
pub static HTTP: LazyLock<ureq::Agent> =
    LazyLock::new(|| ureq::AgentBuilder::new().timeout_connect(Duration::from_secs(10)).timeout(Duration::from_secs(300)).build());

pub struct Server {
    pub child: Child,
    pub url: String,
    /// Held so the server's stdout stays open for as long as it runs.
    _stdout: BufReader<std::process::ChildStdout>,
}

impl Server {
    /// Starts `worldpack serve` on a free port with the store at `store`.
    pub fn start(store: &Path, extra: &[&str]) -> Server {
        Self::start_with_stderr(store, extra, Stdio::inherit())
    }

    /// As [`Server::start`], its standard error (the log) sent to `stderr`.
    pub fn start_with_stderr(store: &Path, extra: &[&str], stderr: Stdio) -> Server {
        Self::start_with(store, extra, stderr, &[])
    }

    /// As [`Server::start`], with `env` set in its environment.
    pub fn start_with(store: &Path, extra: &[&str], stderr: Stdio, env: &[(&str, &str)]) -> Server {
        let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/small");
        let mut args = vec!["serve", "--store", store.to_str().unwrap(), "--steps", "2"];
        if !extra.contains(&"--addr") {
            args.extend(["--addr", "127.0.0.1:0"]);
        }
        if !extra.contains(&"--memory-only") && !extra.contains(&"--model") {
            args.extend(["--model", fixture]);
        }
        args.extend(extra);
        let mut child = Command::new(env!("CARGO_BIN_EXE_worldpack")).args(&args).envs(env.iter().copied()).stdout(Stdio::piped()).stderr(stderr).spawn().unwrap();
        let mut line = String::new();
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        stdout.read_line(&mut line).unwrap();
        let url = line.split("listening on ").nth(1).and_then(|r| r.split_whitespace().next()).unwrap_or_else(|| panic!("no address in {line:?}")).to_string();
        Server { child, url, _stdout: stdout }
    }

    /// Sends SIGTERM and waits up to `within` for the process to exit; its exit status, None if it did not.
    pub fn terminate(&mut self, within: Duration) -> Option<std::process::ExitStatus> {
        unsafe { libc_kill(self.child.id() as i32, 15) };
        let deadline = std::time::Instant::now() + within;
        while std::time::Instant::now() < deadline {
            if let Some(status) = self.child.try_wait().unwrap() {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }

    /// Reads what the server wrote to standard output after its first line.
    pub fn rest_of_stdout(&mut self) -> String {
        let mut out = String::new();
        let _ = self._stdout.read_to_string(&mut out);
        out
    }

    pub fn kill(mut self) {
        let _ = self.child.kill(); // SIGKILL
        let _ = self.child.wait();
    }

    pub fn post(&self, path: &str, body: &Value) -> (u16, Value) {
        answer(HTTP.post(&format!("{}{path}", self.url)).set("Content-Type", "application/json").send_string(&body.to_string()))
    }

    pub fn get(&self, path: &str) -> (u16, Value) {
        answer(HTTP.get(&format!("{}{path}", self.url)).call())
    }

    pub fn bytes(&self, path: &str) -> Vec<u8> {
        let mut out = Vec::new();
        HTTP.get(&format!("{}{path}", self.url)).call().unwrap().into_reader().read_to_end(&mut out).unwrap();
        out
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub fn answer(r: Result<ureq::Response, ureq::Error>) -> (u16, Value) {
    match r {
        Ok(resp) => (resp.status(), resp.into_json().unwrap_or(Value::Null)),
        Err(ureq::Error::Status(code, resp)) => (code, resp.into_json().unwrap_or(Value::Null)),
        Err(e) => panic!("transport error: {e}"),
    }
}

/// Posts a body of `length` bytes, writing until the server stops reading, then reads the answer.
pub fn oversized_post(url: &str, path: &str, length: usize) -> (u16, Value) {
    use std::io::Write;
    let addr = url.trim_start_matches("http://");
    let mut stream = std::net::TcpStream::connect(addr).unwrap();
    write!(stream, "POST {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\nContent-Length: {length}\r\n\r\n").unwrap();
    let chunk = vec![b'x'; 1 << 16];
    let mut sent = 0;
    while sent < length {
        let n = chunk.len().min(length - sent);
        if stream.write_all(&chunk[..n]).is_err() {
            break; // the server answered and closed
        }
        sent += n;
    }
    stream.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut reader = BufReader::new(stream);
    let mut status = String::new();
    reader.read_line(&mut status).unwrap();
    let code: u16 = status.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or_else(|| panic!("no status in {status:?}"));
    let mut body_len = 0;
    loop {
        let mut line = String::new();
        reader.read_line(&mut line).unwrap();
        if line.trim().is_empty() {
            break;
        }
        if let Some(v) = line.to_ascii_lowercase().strip_prefix("content-length:") {
            body_len = v.trim().parse().unwrap();
        }
    }
    let mut body = vec![0; body_len];
    reader.read_exact(&mut body).unwrap();
    (code, serde_json::from_slice(&body).unwrap_or(Value::Null))
}

pub fn temp_store(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("worldpack-serve-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir.join("store.redb")
}

pub fn c2w(position: [f64; 3]) -> Value {
    json!({ "c2w": { "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "position": position } })
}

pub struct PgCluster {
    pub dir: PathBuf,
    pub port: u16,
}

impl PgCluster {
    pub fn bin(name: &str) -> PathBuf {
        let debian = Path::new("/usr/lib/postgresql/15/bin").join(name);
        if debian.exists() { debian } else { PathBuf::from(name) }
    }

    pub fn as_owner(program: PathBuf) -> Command {
        // SAFETY: geteuid has no preconditions.
        if unsafe { libc_geteuid() } == 0 {
            let mut c = Command::new("runuser");
            c.args(["-u", "postgres", "--"]).arg(program);
            c
        } else {
            Command::new(program)
        }
    }

    pub fn run(mut c: Command, what: &str) {
        let out = c.output().unwrap_or_else(|e| panic!("{what}: {e} (PostgreSQL 15 must be installed)"));
        assert!(out.status.success(), "{what}: {}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    }

    pub fn start(name: &str) -> PgCluster {
        let dir = std::env::temp_dir().join(format!("worldpack-pg-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        if unsafe { libc_geteuid() } == 0 {
            Self::run({ let mut c = Command::new("chown"); c.args(["-R", "postgres:postgres"]).arg(&dir); c }, "chown");
        }
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let data = dir.join("data");
        let mut init = Self::as_owner(Self::bin("initdb"));
        init.args(["-A", "trust", "-U", "postgres", "-D"]).arg(&data);
        Self::run(init, "initdb");
        let mut ctl = Self::as_owner(Self::bin("pg_ctl"));
        ctl.arg("-D").arg(&data).arg("-l").arg(dir.join("log")).arg("-w").arg("-o")
            .arg(format!("-p {port} -c listen_addresses=127.0.0.1 -k {}", dir.display())).arg("start");
        Self::run(ctl, "pg_ctl start");
        PgCluster { dir, port }
    }

    pub fn url(&self) -> PathBuf {
        PathBuf::from(format!("postgres://postgres@127.0.0.1:{}/postgres", self.port))
    }
}

impl PgCluster {
    pub fn stop(&self) {
        let mut ctl = Self::as_owner(Self::bin("pg_ctl"));
        ctl.arg("-D").arg(self.dir.join("data")).args(["-m", "fast", "-w", "stop"]);
        Self::run(ctl, "pg_ctl stop");
    }

    pub fn restart(&self) {
        let mut ctl = Self::as_owner(Self::bin("pg_ctl"));
        ctl.arg("-D").arg(self.dir.join("data")).arg("-l").arg(self.dir.join("log")).arg("-w").arg("-o")
            .arg(format!("-p {} -c listen_addresses=127.0.0.1 -k {}", self.port, self.dir.display())).arg("start");
        Self::run(ctl, "pg_ctl start");
    }
}

impl Drop for PgCluster {
    fn drop(&mut self) {
        let mut ctl = Self::as_owner(Self::bin("pg_ctl"));
        ctl.arg("-D").arg(self.dir.join("data")).args(["-m", "immediate", "stop"]);
        let _ = ctl.output();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

unsafe extern "C" {
    #[link_name = "geteuid"]
    pub fn libc_geteuid() -> u32;
    #[link_name = "kill"]
    pub fn libc_kill(pid: i32, signal: i32) -> i32;
}

