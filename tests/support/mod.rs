//! What the server tests share: a real `worldpack serve` on loopback, HTTP
//! with timeouts, temporary stores and a PostgreSQL cluster of their own.
#![allow(dead_code)] // each test binary uses its own part of this

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{LazyLock, Mutex};
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
        terminate(&mut self.child, within)
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
        Self::start_with(name, None)
    }

    /// A cluster that takes TCP connections over TLS only, its certificate
    /// issued for `names` (`subjectAltName`, e.g. "IP:127.0.0.1") by a CA of
    /// its own, [`PgCluster::ca`].
    pub fn start_tls(name: &str, names: &str) -> PgCluster {
        Self::start_with(name, Some(names))
    }

    fn start_with(name: &str, tls_names: Option<&str>) -> PgCluster {
        let dir = std::env::temp_dir().join(format!("worldpack-pg-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        if let Some(names) = tls_names {
            Self::issue_certificate(&dir, names);
        }
        if unsafe { libc_geteuid() } == 0 {
            Self::run({ let mut c = Command::new("chown"); c.args(["-R", "postgres:postgres"]).arg(&dir); c }, "chown");
        }
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let data = dir.join("data");
        let mut init = Self::as_owner(Self::bin("initdb"));
        init.args(["-A", "trust", "-U", "postgres", "-D"]).arg(&data);
        Self::run(init, "initdb");
        let cluster = PgCluster { dir, port };
        if tls_names.is_some() {
            std::fs::write(data.join("pg_hba.conf"), "local all all trust\nhostssl all all 127.0.0.1/32 trust\n").unwrap();
        }
        cluster.restart();
        cluster
    }

    /// A CA (ca.crt) and the server's key and certificate for `names`, signed by it.
    fn issue_certificate(dir: &Path, names: &str) {
        let openssl = |args: &[&str]| {
            let mut c = Command::new("openssl");
            c.current_dir(dir).args(args);
            Self::run(c, "openssl");
        };
        let ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"];
        openssl(&[&["req", "-x509"][..], &ec, &["-keyout", "ca.key", "-out", "ca.crt", "-days", "2", "-subj", "/CN=worldpack test CA"]].concat());
        openssl(&[&["req"][..], &ec, &["-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=worldpack test database"]].concat());
        std::fs::write(dir.join("server.ext"), format!("subjectAltName={names}\nbasicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n")).unwrap();
        openssl(&["x509", "-req", "-in", "server.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial", "-out", "server.crt", "-days", "2", "-extfile", "server.ext"]);
        std::fs::set_permissions(dir.join("server.key"), std::os::unix::fs::PermissionsExt::from_mode(0o600)).unwrap();
    }

    /// The CA that issued a TLS cluster's certificate (PEM).
    pub fn ca(&self) -> PathBuf {
        self.dir.join("ca.crt")
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
        let mut options = format!("-p {} -c listen_addresses=127.0.0.1 -k {}", self.port, self.dir.display());
        if self.dir.join("server.crt").exists() {
            options += &format!(" -c ssl=on -c ssl_cert_file={0}/server.crt -c ssl_key_file={0}/server.key", self.dir.display());
        }
        let mut ctl = Self::as_owner(Self::bin("pg_ctl"));
        ctl.arg("-D").arg(self.dir.join("data")).arg("-l").arg(self.dir.join("log")).arg("-w").arg("-o").arg(options).arg("start");
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

/// How long a Triton host may take to load a model folder's graphs.
pub const TRITON_START: Duration = Duration::from_secs(240);

/// How long a Triton host may take to stop tidily (it takes ~8 s).
pub const TRITON_STOP: Duration = Duration::from_secs(30);

/// The Triton tests run one at a time: each host loads every graph in its
/// own Python and Triton processes, and several at once beside the other
/// servers starve a small CI machine.
pub fn triton_alone() -> std::sync::MutexGuard<'static, ()> {
    static ONE: Mutex<()> = Mutex::new(());
    ONE.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// `serving/triton/host.py`: a real Triton Inference Server (PyPI's
/// `tritonserver`, in `.venv-triton`, which scripts/test.sh makes) hosting a
/// model folder's graphs on free loopback ports; killed with its process
/// group on drop.
pub struct TritonHost {
    child: Child,
    stopped: bool,
    pub ports: [u16; 3],
    _stdout: BufReader<std::process::ChildStdout>,
}

impl TritonHost {
    /// Starts it on `ports` (http, grpc, metrics) or on free ones. A start
    /// on free ports that fails (another process took one of them between
    /// the probe and Triton's bind) is tried once more on new ones.
    pub fn start(model: &str, ports: Option<[u16; 3]>) -> TritonHost {
        let free = || std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        match (TritonHost::try_start(model, ports.unwrap_or_else(|| [free(), free(), free()])), ports) {
            (Ok(host), _) => host,
            (Err(why), Some(_)) => panic!("{why}"),
            (Err(why), None) => {
                eprintln!("{why}; trying once more on other ports");
                TritonHost::try_start(model, [free(), free(), free()]).unwrap_or_else(|why| panic!("{why}"))
            }
        }
    }

    /// Waits at most [`TRITON_START`] for `serving/triton/host.py` to say it
    /// serves; otherwise kills it and returns why, with the end of its log.
    fn try_start(model: &str, [http, grpc, metrics]: [u16; 3]) -> Result<TritonHost, String> {
        use std::os::unix::process::CommandExt;
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let python = std::env::var_os("WORLDPACK_TRITON_PYTHON").map(PathBuf::from).unwrap_or(root.join(".venv-triton/bin/python"));
        assert!(python.exists(), "{} is missing: run ./scripts/test.sh once (it makes .venv-triton with PyPI's nvidia-pytriton)", python.display());
        let log = std::env::temp_dir().join(format!("worldpack-triton-{}-{http}.log", std::process::id()));
        let mut child = Command::new(python)
            .arg(root.join("serving/triton/host.py"))
            .arg("--model").arg(root.join(model))
            .args(["--http-port", &http.to_string(), "--grpc-port", &grpc.to_string(), "--metrics-port", &metrics.to_string()])
            .args(["--exit-timeout-secs", "2"]) // nothing in flight is worth waiting for when a test stops it
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).unwrap())
            .process_group(0)
            .spawn()
            .unwrap();
        // Its stdout's one line, "serving ...", read on a thread so that the wait has a
        // deadline. Anything else there (tritonserver's log belongs on stderr) fails the start.
        let (said, heard) = std::sync::mpsc::channel();
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        std::thread::spawn(move || {
            let mut line = String::new();
            if stdout.read_line(&mut line).unwrap_or(0) == 0 {
                return; // dropping `said` reports the exit
            }
            let _ = said.send(if line.starts_with("serving ") { Ok(stdout) } else { Err(line) });
        });
        match heard.recv_timeout(TRITON_START) {
            Ok(Ok(stdout)) => Ok(TritonHost { child, stopped: false, ports: [http, grpc, metrics], _stdout: stdout }),
            Ok(Err(line)) => {
                stop_group(&mut child);
                panic!("serving/triton/host.py wrote {line:?} to stdout, which carries its \"serving\" line alone");
            }
            Err(waited) => {
                stop_group(&mut child);
                let text = std::fs::read_to_string(&log).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(15).collect::<Vec<_>>().into_iter().rev().collect();
                let how = match waited {
                    std::sync::mpsc::RecvTimeoutError::Timeout => format!("did not serve within {TRITON_START:?}"),
                    std::sync::mpsc::RecvTimeoutError::Disconnected => "exited before serving".into(),
                };
                Err(format!("serving/triton/host.py on ports {http}/{grpc}/{metrics} {how}; the end of its log ({}):\n{}", log.display(), tail.join("\n")))
            }
        }
    }

    /// The host's process id (its shared memory is named after it).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The `--model-backend` URL.
    pub fn backend(&self) -> String {
        format!("triton://127.0.0.1:{}", self.ports[0])
    }

    /// A counter from Triton's Prometheus metrics for one model.
    pub fn metric(&self, name: &str, model: &str) -> f64 {
        let text = HTTP.get(&format!("http://127.0.0.1:{}/metrics", self.ports[2])).call().unwrap().into_string().unwrap();
        let prefix = format!("{name}{{model=\"{model}\",");
        text.lines().find(|l| l.starts_with(&prefix)).and_then(|l| l.rsplit(' ').next()).and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no {prefix} in Triton's metrics"))
    }

    /// SIGTERM first, so that the host stops tritonserver and removes its
    /// shared memory and workspace (a kill leaves them in /dev/shm and
    /// ~/.cache/pytriton, ~20 MB a start); the whole group is killed after.
    pub fn stop(&mut self) {
        if !self.stopped {
            stop_group(&mut self.child); // once: a reaped pid may be another process's by now
            self.stopped = true;
        }
    }
}

/// Sends `child` SIGTERM and waits up to `within` for it to exit; its exit status, None if it did not.
pub fn terminate(child: &mut Child, within: Duration) -> Option<std::process::ExitStatus> {
    unsafe { libc_kill(child.id() as i32, 15) };
    let deadline = std::time::Instant::now() + within;
    while std::time::Instant::now() < deadline {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

/// SIGTERM to a process group's leader, up to [`TRITON_STOP`] to exit, then
/// SIGKILL to the whole group (python and tritonserver).
fn stop_group(child: &mut Child) {
    let pid = child.id() as i32;
    if terminate(child, TRITON_STOP).is_none() {
        eprintln!("the Triton host {pid} did not stop within {TRITON_STOP:?} of SIGTERM; killing its group");
    }
    unsafe { libc_kill(-pid, 9) };
    let _ = child.wait();
}

impl Drop for TritonHost {
    fn drop(&mut self) {
        self.stop();
    }
}
