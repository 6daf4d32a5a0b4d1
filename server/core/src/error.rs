//! The core's errors. Each carries a stable `code` (the API's error code, part of the public
//! contract) and a message that names the offending field, value or G-code line; `kind` says what
//! sort of failure it is, so an outer layer can map it (the HTTP layer maps kinds to statuses)
//! without the core knowing about HTTP.

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorKind {
    /// The request itself is malformed (empty body, bad query).
    BadRequest,
    /// Well-formed but refused: a field, a G-code line, a limit.
    Invalid,
    NotFound,
    /// The current state forbids it (busy machine, finished job, name taken).
    Conflict,
    /// Larger than a configured limit.
    TooLarge,
    /// The machine cannot take calls now (offline, unresponsive, shutting down).
    Unavailable,
    /// The backend did not answer in time.
    Timeout,
    /// The backend answered something unusable.
    Backend,
    Internal,
}

#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct Error {
    pub kind: ErrorKind,
    pub code: &'static str,
    pub message: String,
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Longest name of a machine, pendant, job or token, in characters.
pub const MAX_NAME_CHARS: usize = 100;

impl Error {
    pub fn new(kind: ErrorKind, code: &'static str, message: impl Into<String>) -> Self {
        Error {
            kind,
            code,
            message: message.into(),
        }
    }
    pub fn bad_request(code: &'static str, m: impl Into<String>) -> Self {
        Self::new(ErrorKind::BadRequest, code, m)
    }
    pub fn invalid(code: &'static str, m: impl Into<String>) -> Self {
        Self::new(ErrorKind::Invalid, code, m)
    }
    pub fn not_found(code: &'static str, m: impl Into<String>) -> Self {
        Self::new(ErrorKind::NotFound, code, m)
    }
    pub fn conflict(code: &'static str, m: impl Into<String>) -> Self {
        Self::new(ErrorKind::Conflict, code, m)
    }
    pub fn internal(m: impl Into<String>) -> Self {
        Self::new(ErrorKind::Internal, "internal", m)
    }

    /// The `name` field of something being created, trimmed; empty is refused naming the field.
    pub fn required_name(name: &str) -> Result<&str> {
        let name = Self::valid_name("name", name)?;
        if name.is_empty() {
            return Err(Error::invalid(
                "invalid_field",
                "field `name` must not be empty",
            ));
        }
        Ok(name)
    }

    /// A name as people read it in lists, logs and `/metrics`: trimmed, at most
    /// [`MAX_NAME_CHARS`] characters, no control characters (a NUL or a newline would corrupt
    /// every place it is shown).
    pub fn valid_name<'a>(field: &str, name: &'a str) -> Result<&'a str> {
        let name = name.trim();
        let chars = name.chars().count();
        if chars > MAX_NAME_CHARS {
            return Err(Error::invalid(
                "invalid_field",
                format!("field `{field}` is at most {MAX_NAME_CHARS} characters, got {chars}"),
            ));
        }
        if let Some((i, c)) = name.chars().enumerate().find(|(_, c)| c.is_control()) {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `{field}` must not contain control characters: U+{:04X} at character {}",
                    c as u32,
                    i + 1
                ),
            ));
        }
        Ok(name)
    }

    /// A failed insert of a named thing: a clash with an existing name is `name_taken`;
    /// anything else is a database error.
    pub fn insert_failed(e: sqlx::Error, what: &str, name: &str) -> Error {
        match e {
            sqlx::Error::Database(d) if d.is_unique_violation() => Error::conflict(
                "name_taken",
                format!("a {what} named {name:?} already exists"),
            ),
            other => other.into(),
        }
    }
}

impl From<sqlx::Error> for Error {
    fn from(e: sqlx::Error) -> Self {
        tracing::error!(error = %e, "database error");
        if is_unreachable(&e) {
            return Error::new(
                ErrorKind::Unavailable,
                "database_unavailable",
                format!("the database is unreachable: {e}"),
            );
        }
        Error::internal(format!("database error: {e}"))
    }
}

/// Whether an error means the database cannot take our writes (as opposed to a refused
/// statement): see [`outage_reason`].
pub fn is_unreachable(e: &sqlx::Error) -> bool {
    outage_reason(e).is_some()
}

/// Why the database counts as down after `e`, as `/healthz` and refusals say it, or `None` for
/// an error that is the statement's own (a constraint, a bad row). An outage: the connection or
/// pool failed; PostgreSQL is shutting down or refusing connections (SQLSTATE classes 08 and
/// 57P, 53300 too many connections), its disk is full (53100), an I/O error outside it (class
/// 58) or it is a read-only standby (25006); SQLite cannot write its file: full (13), I/O error
/// (10), read-only (8), cannot open it (14), locked past the busy timeout (5, 6).
pub fn outage_reason(e: &sqlx::Error) -> Option<String> {
    let class = match e {
        sqlx::Error::Io(_)
        | sqlx::Error::Tls(_)
        | sqlx::Error::Protocol(_)
        | sqlx::Error::PoolTimedOut
        | sqlx::Error::PoolClosed
        | sqlx::Error::WorkerCrashed => None,
        sqlx::Error::Database(d) => {
            let code = d.code().unwrap_or_default();
            // PostgreSQL's SQLSTATE is always five characters (and may be all digits: 53100);
            // SQLite's (extended) result code is a number below 10000 whose low byte is the
            // primary code.
            if code.len() == 5 {
                match code.as_ref() {
                    "53100" => Some("disk full"),
                    "25006" => Some("read-only"),
                    c if c.starts_with("58") => Some("I/O error"),
                    c if c.starts_with("08") || c.starts_with("57P") || c == "53300" => None,
                    _ => return None,
                }
            } else {
                match code.parse::<i64>().map(|n| n & 0xff) {
                    Ok(13) => Some("disk full"),
                    Ok(10) => Some("I/O error"),
                    Ok(8) => Some("read-only"),
                    Ok(14) => Some("cannot open the database file"),
                    Ok(5 | 6) => Some("locked"),
                    _ => return None,
                }
            }
        }
        _ => return None,
    };
    Some(match class {
        Some(class) => format!("{class}: {e}"),
        None => e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_bounded_and_free_of_control_characters() {
        assert_eq!(Error::required_name("  mill 1 ").ok(), Some("mill 1"));
        assert!(Error::required_name("   ").is_err());
        let long = "x".repeat(MAX_NAME_CHARS + 1);
        assert!(Error::required_name(&long).is_err_and(|e| e.message.contains("at most")));
        assert!(Error::required_name("a\0b").is_err_and(|e| e.message.contains("U+0000")));
        assert!(Error::required_name("a\nb").is_err());
        assert!(Error::required_name("fresadora ñ").is_ok());
    }

    /// A database error with only a code, as the drivers report them.
    #[derive(Debug)]
    struct Coded(&'static str);
    impl std::fmt::Display for Coded {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "error {}", self.0)
        }
    }
    impl std::error::Error for Coded {}
    impl sqlx::error::DatabaseError for Coded {
        fn message(&self) -> &str {
            self.0
        }
        fn code(&self) -> Option<std::borrow::Cow<'_, str>> {
            Some(self.0.into())
        }
        fn as_error(&self) -> &(dyn std::error::Error + Send + Sync + 'static) {
            self
        }
        fn as_error_mut(&mut self) -> &mut (dyn std::error::Error + Send + Sync + 'static) {
            self
        }
        fn into_error(self: Box<Self>) -> Box<dyn std::error::Error + Send + Sync + 'static> {
            self
        }
        fn kind(&self) -> sqlx::error::ErrorKind {
            sqlx::error::ErrorKind::Other
        }
    }

    /// The outage reason for a database error with `code`, without sqlx's own prefix.
    fn reason(code: &'static str) -> Option<String> {
        outage_reason(&sqlx::Error::Database(Box::new(Coded(code))))
            .map(|r| r.replace("error returned from database: ", ""))
    }

    #[test]
    fn a_full_read_only_or_failing_disk_is_an_outage_named_by_its_cause() {
        // SQLite: FULL, IOERR_WRITE (778), READONLY, CANTOPEN; PostgreSQL: disk_full, io_error.
        assert_eq!(reason("13").as_deref(), Some("disk full: error 13"));
        assert_eq!(reason("778").as_deref(), Some("I/O error: error 778"));
        assert_eq!(reason("8").as_deref(), Some("read-only: error 8"));
        assert!(reason("14").is_some_and(|r| r.starts_with("cannot open")));
        assert_eq!(reason("53100").as_deref(), Some("disk full: error 53100"));
        assert_eq!(reason("58030").as_deref(), Some("I/O error: error 58030"));
        assert_eq!(reason("08006").as_deref(), Some("error 08006"));
        assert_eq!(reason("57P01").as_deref(), Some("error 57P01"));
        // SQLite's BUSY_SNAPSHOT (517): locked.
        assert_eq!(reason("517").as_deref(), Some("locked: error 517"));
        // A constraint is the statement's fault, not an outage: SQLite's CONSTRAINT_UNIQUE
        // (2067), PostgreSQL's unique_violation.
        assert_eq!(reason("2067"), None);
        assert_eq!(reason("23505"), None);
        assert_eq!(outage_reason(&sqlx::Error::RowNotFound), None);
    }
}
