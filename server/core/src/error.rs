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

/// Whether an error means the database cannot be reached (as opposed to a refused statement):
/// the connection or pool failed, PostgreSQL is shutting down or refusing connections
/// (SQLSTATE classes 08 and 57P), or SQLite cannot write its file (full, I/O error, locked).
pub fn is_unreachable(e: &sqlx::Error) -> bool {
    match e {
        sqlx::Error::Io(_)
        | sqlx::Error::Tls(_)
        | sqlx::Error::Protocol(_)
        | sqlx::Error::PoolTimedOut
        | sqlx::Error::PoolClosed
        | sqlx::Error::WorkerCrashed => true,
        sqlx::Error::Database(d) => {
            let code = d.code().unwrap_or_default();
            // SQLite reports its (extended) result code as a number; the primary code is the
            // low byte: 5 BUSY, 6 LOCKED, 10 IOERR, 13 FULL, 14 CANTOPEN.
            match code.parse::<i64>() {
                Ok(n) => matches!(n & 0xff, 5 | 6 | 10 | 13 | 14),
                Err(_) => code.starts_with("08") || code.starts_with("57P"),
            }
        }
        _ => false,
    }
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
}
