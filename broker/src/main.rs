//! `fbbus`: the line broker and its tools.

use std::io::BufRead;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use broker::{Broker, Config};
use clap::{Args, Parser, Subcommand};
use security::{Argon2Params, PasswordFile, StoredHash};

mod admin_client;
#[cfg(feature = "bridge")]
mod bus_cert;
mod devices_command;
mod profile_command;
mod sessions_command;
mod terminal_table;
#[cfg(feature = "bridge")]
mod zenohd_command;

/// The allocator and its options: see the broker library's `memory` module for why these.
#[cfg(feature = "jemalloc")]
#[global_allocator]
static ALLOCATOR: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

/// jemalloc reads this C string before `main` (its `malloc_conf`, under the prefix
/// tikv-jemallocator builds it with); `_RJEM_MALLOC_CONF` in the environment still
/// overrides it.
#[cfg(feature = "jemalloc")]
#[unsafe(export_name = "_rjem_malloc_conf")]
pub static JEMALLOC_CONF: &[u8; 125] = broker::JEMALLOC_CONF;

#[derive(Parser)]
#[command(
    name = "fbbus",
    version,
    about = "fbbus: the message bus for IEC 61499 function-block devices"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the line broker (MQTT 3.1.1 and 5). Without --config: loopback port 1883,
    /// anonymous, admin HTTP on 127.0.0.1:9883.
    Serve {
        /// TOML configuration file (see deploy/fbbus.example.toml).
        #[arg(long, short)]
        config: Option<PathBuf>,
    },
    /// Validate a configuration file and exit: 0 if fbbus would start with it.
    CheckConfig { config: PathBuf },
    /// Manage an argon2id password file, like mosquitto_passwd.
    Passwd(PasswdArgs),
    /// Show the device registry of a running broker (from its admin endpoint), or
    /// `forget` a device. An admin endpoint with `[admin] password_file` takes the
    /// credentials from FBBUS_ADMIN_USER and FBBUS_ADMIN_PASSWORD in the environment.
    #[command(args_conflicts_with_subcommands = true)]
    Devices {
        #[command(subcommand)]
        action: Option<DevicesAction>,
        /// One device's record instead of the list.
        id: Option<String>,
        #[command(flatten)]
        endpoint: AdminEndpoint,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        /// Redraw every second until interrupted.
        #[arg(long)]
        watch: bool,
    },
    /// Show the sessions of a running broker (connected and kept offline) with the user
    /// that owns each, or `drop` a kept one so that its client id is free again.
    /// Credentials as for `devices`.
    #[command(args_conflicts_with_subcommands = true)]
    Sessions {
        #[command(subcommand)]
        action: Option<SessionsAction>,
        #[command(flatten)]
        endpoint: AdminEndpoint,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Put a device profile (TOML) into a running broker from its host: checked against
    /// every other profile, written into its profiles directory, in force at once.
    /// Credentials, for an admin endpoint with `[admin] password_file`: FBBUS_ADMIN_USER
    /// and FBBUS_ADMIN_PASSWORD in the environment.
    Declare {
        /// The profile file (docs/runtimes.md).
        file: PathBuf,
        #[command(flatten)]
        endpoint: AdminEndpoint,
    },
    /// Device profiles without a broker: check one, or derive them from a 4diac boot file
    /// (FORTE's, or a DINASORE's data_model.fboot).
    Profile {
        #[command(subcommand)]
        action: ProfileAction,
    },
    /// Create the plant's bus CA and the certificates of lines, zenoh routers and zenoh
    /// applications, for mutual TLS on the bus (docs/bus-security.md).
    #[cfg(feature = "bridge")]
    BusCert {
        #[command(subcommand)]
        action: bus_cert::Action,
    },
    /// Print the configuration of the plant's zenoh router (`zenohd -c`): mutual TLS and
    /// the same access control the lines apply (docs/bus-security.md).
    #[cfg(feature = "bridge")]
    ZenohdConfig(zenohd_command::ZenohdArgs),
}

#[derive(Subcommand)]
enum DevicesAction {
    /// Remove an offline device from the registry of a running broker, with its retained
    /// record and values and its metric series (from the broker's host only; an online
    /// device is refused).
    Forget {
        id: String,
        #[command(flatten)]
        endpoint: AdminEndpoint,
    },
}

#[derive(Subcommand)]
enum SessionsAction {
    /// End the kept offline session of a client id, as its expiry would (from the
    /// broker's host only; a connected session is refused): for a device locked out by a
    /// session another user left under its client id.
    Drop {
        client_id: String,
        #[command(flatten)]
        endpoint: AdminEndpoint,
    },
}

#[derive(Subcommand)]
enum ProfileAction {
    /// Validate a profile file: every mistake, each with its key.
    Check { file: PathBuf },
    /// Derive profiles from a 4diac boot file (.fboot: a FORTE boot file, or the
    /// resources/data_model.fboot of a DINASORE) and print them as TOML, with what could
    /// not be derived.
    Import(profile_command::ImportArgs),
}

#[derive(Args)]
struct PasswdArgs {
    /// The password file (created by `add` if missing).
    file: PathBuf,
    #[command(subcommand)]
    action: PasswdAction,
}

#[derive(Subcommand)]
enum PasswdAction {
    /// Add a user (or, with --force, change its password). The password is read from a
    /// no-echo prompt, or with --stdin from the first line of standard input; never from
    /// the command line.
    Add {
        user: String,
        #[arg(long)]
        stdin: bool,
        /// Replace the password of a user the file already has. Without it that is
        /// refused: a mistyped new device name must not change another device's password.
        #[arg(long)]
        force: bool,
        /// argon2id memory cost in KiB (default 8192).
        #[arg(long)]
        memory_kib: Option<u32>,
        /// argon2id iterations (default 1).
        #[arg(long)]
        iterations: Option<u32>,
    },
    /// Remove a user.
    Delete { user: String },
    /// List the users (names only) and the kind of hash each has.
    List,
    /// Copy the users of a Mosquitto password file ($7$ PBKDF2-SHA512 or $6$ SHA-512)
    /// into this file; each is rewritten as argon2id at its next successful login.
    Import {
        mosquitto_file: PathBuf,
        /// Replace users that already exist in this file.
        #[arg(long)]
        overwrite: bool,
    },
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve { config } => serve(config),
        Command::CheckConfig { config } => check_config(&config),
        Command::Passwd(args) => passwd(args),
        #[cfg(feature = "bridge")]
        Command::ZenohdConfig(args) => zenohd_command::run(args),
        Command::Devices {
            action: Some(DevicesAction::Forget { id, endpoint }),
            ..
        } => endpoint
            .address()
            .and_then(|a| devices_command::forget(a, &id)),
        Command::Devices {
            action: None,
            id,
            endpoint,
            json,
            watch,
        } => endpoint.address().and_then(|admin| {
            devices_command::run(devices_command::Options {
                admin,
                json,
                watch: watch.then_some(Duration::from_secs(1)),
                id,
            })
        }),
        Command::Sessions {
            action:
                Some(SessionsAction::Drop {
                    client_id,
                    endpoint,
                }),
            ..
        } => endpoint
            .address()
            .and_then(|a| sessions_command::drop(a, &client_id)),
        Command::Sessions {
            action: None,
            endpoint,
            json,
        } => endpoint
            .address()
            .and_then(|a| sessions_command::list(a, json)),
        Command::Declare { file, endpoint } => endpoint
            .address()
            .and_then(|a| profile_command::declare(&file, a)),
        Command::Profile { action } => match action {
            ProfileAction::Check { file } => profile_command::check(&file),
            ProfileAction::Import(args) => profile_command::import(&args),
        },
        #[cfg(feature = "bridge")]
        Command::BusCert { action } => bus_cert::run(action),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fbbus: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Validates the file and loads everything it names (password file, ACL, TLS files).
fn check_config(path: &std::path::Path) -> Result<()> {
    let config = Config::load(path)?;
    broker::check_config(&config)?;
    println!("{}: ok", path.display());
    Ok(())
}

/// The exit status when a core part of the broker died (EX_SOFTWARE): the service manager
/// restarts on it; a configuration error exits with 1 before anything was served.
const EXIT_FATAL: i32 = 70;

fn serve(config_path: Option<PathBuf>) -> Result<()> {
    let config = match &config_path {
        Some(path) => Config::load(path)?,
        None => Config::embedded_default(),
    };
    broker::init_logging(&config.log).map_err(anyhow::Error::msg)?;
    broker::install_panic_hook();
    broker::configure_memory();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let workers = config.broker.workers(cores);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("fbbus")
        .worker_threads(workers)
        .build()
        .context("cannot start the tokio runtime")?;
    let served = runtime.block_on(async move {
        match &config_path {
            Some(p) => tracing::info!(
                config = %p.display(),
                line = config.broker.line,
                workers,
                cores,
                "starting"
            ),
            None => tracing::info!(
                line = config.broker.line,
                workers,
                cores,
                "starting on the embedded default configuration (loopback only)"
            ),
        }
        let broker = Broker::start(config).await?;
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .context("cannot listen for SIGTERM")?;
        let died = tokio::select! {
            _ = term.recv() => { tracing::info!("SIGTERM: shutting down"); None }
            _ = tokio::signal::ctrl_c() => { tracing::info!("SIGINT: shutting down"); None }
            reason = broker.died() => Some(reason),
        };
        if let Some(reason) = died {
            // The router or another core part is gone: nothing can be routed or closed
            // cleanly any more. Keep what the registry knows and exit at once, non-zero,
            // so the service manager starts a whole broker (`Restart=on-failure`).
            broker.abort().await;
            tracing::error!(reason, status = EXIT_FATAL, "fbbus stops");
            eprintln!("fbbus: stopped: {reason}");
            std::process::exit(EXIT_FATAL);
        }
        broker.shutdown(Duration::from_secs(5)).await;
        Ok(())
    });
    // A zenoh client still waiting for its router holds a blocking thread (zenoh's `open`
    // cannot be cancelled): do not wait for it.
    runtime.shutdown_timeout(Duration::from_secs(1));
    served
}

fn passwd(args: PasswdArgs) -> Result<()> {
    let file = &args.file;
    let load_or_new = || -> Result<PasswordFile> {
        if file.exists() {
            Ok(PasswordFile::load(file)?)
        } else {
            Ok(PasswordFile::default())
        }
    };
    match args.action {
        PasswdAction::Add {
            user,
            stdin,
            force,
            memory_kib,
            iterations,
        } => {
            let mut params = Argon2Params::default();
            if let Some(m) = memory_kib {
                params.memory_kib = m;
            }
            if let Some(t) = iterations {
                params.iterations = t;
            }
            params.validate()?;
            let mut pf = load_or_new()?;
            let existed = pf.get(&user).is_some();
            if existed && !force {
                bail!(
                    "{0}: user `{user}` already exists; nothing changed. To replace its \
                     password: fbbus passwd {0} add {user} --force",
                    file.display()
                );
            }
            let password = read_password(stdin)?;
            let phc = security::hash_password(password.as_bytes(), &params)?;
            pf.set(&user, StoredHash::parse(&phc)?)?;
            pf.save(file)?;
            let what = if existed {
                "password replaced"
            } else {
                "added"
            };
            eprintln!("{}: user `{user}` {what} (argon2id)", file.display());
        }
        PasswdAction::Delete { user } => {
            let mut pf = PasswordFile::load(file)?;
            if !pf.remove(&user) {
                bail!("{}: no user `{user}`", file.display());
            }
            pf.save(file)?;
            eprintln!("{}: user `{user}` deleted", file.display());
        }
        PasswdAction::List => {
            let pf = PasswordFile::load(file)?;
            for user in pf.users() {
                let kind = match pf.get(user) {
                    Some(h) if h.is_legacy() => "mosquitto (rehashed to argon2id at next login)",
                    _ => "argon2id",
                };
                println!("{user}\t{kind}");
            }
        }
        PasswdAction::Import {
            mosquitto_file,
            overwrite,
        } => {
            let source = PasswordFile::load(&mosquitto_file)?;
            let mut pf = load_or_new()?;
            let (added, skipped) = pf.merge_from(&source, overwrite);
            pf.save(file)?;
            eprintln!(
                "{}: imported {added} user(s) from {}, skipped {skipped} existing",
                file.display(),
                mosquitto_file.display()
            );
        }
    }
    Ok(())
}

/// Reads a new password without echo (twice, to catch typos), or one line from stdin.
fn read_password(from_stdin: bool) -> Result<String> {
    let password = if from_stdin {
        let mut line = String::new();
        std::io::stdin()
            .lock()
            .read_line(&mut line)
            .context("cannot read the password from standard input")?;
        line.trim_end_matches(['\n', '\r']).to_owned()
    } else {
        let first = rpassword::prompt_password("Password: ")
            .context("cannot read the password from the terminal (use --stdin in scripts)")?;
        let second = rpassword::prompt_password("Reenter password: ")?;
        if first != second {
            bail!("the passwords do not match; nothing changed");
        }
        first
    };
    if password.is_empty() {
        bail!("empty password refused; nothing changed");
    }
    Ok(password)
}

/// The admin endpoint: `--admin`, else the one `--config` names, else the default.
/// Which admin endpoint a command talks to (`devices`, `sessions`, `declare`).
#[derive(clap::Args)]
struct AdminEndpoint {
    /// The admin endpoint; default: the one --config names, else 127.0.0.1:9883.
    #[arg(long)]
    admin: Option<std::net::SocketAddr>,
    /// Take the admin endpoint from this configuration file.
    #[arg(long, short)]
    config: Option<PathBuf>,
}

impl AdminEndpoint {
    fn address(self) -> Result<std::net::SocketAddr> {
        Ok(match (self.admin, self.config) {
            (Some(a), _) => a,
            (None, Some(path)) => Config::load(&path)?.admin.bind,
            (None, None) => Config::embedded_default().admin.bind,
        })
    }
}
