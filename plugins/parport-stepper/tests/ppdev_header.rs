//! The ppdev ioctl numbers in `port::ppdev` are written by hand; this compiles the system
//! header `<linux/ppdev.h>` with the C compiler (`$CC`, default `cc`) and compares.

#![cfg(target_os = "linux")]
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_parport_stepper::port::ppdev;
use std::process::Command;

#[test]
fn ioctl_numbers_match_linux_ppdev_h() {
    let dir = std::env::temp_dir().join(format!("ppdev-header-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let src = dir.join("ppdev.c");
    let exe = dir.join("ppdev");
    std::fs::write(
        &src,
        r#"#include <stdio.h>
#include <sys/ioctl.h>
#include <linux/ppdev.h>
int main(void) {
    printf("PPCLAIM %lu\n", (unsigned long)PPCLAIM);
    printf("PPRELEASE %lu\n", (unsigned long)PPRELEASE);
    printf("PPEXCL %lu\n", (unsigned long)PPEXCL);
    printf("PPRSTATUS %lu\n", (unsigned long)PPRSTATUS);
    printf("PPWCONTROL %lu\n", (unsigned long)PPWCONTROL);
    printf("PPWDATA %lu\n", (unsigned long)PPWDATA);
    return 0;
}
"#,
    )
    .unwrap();
    let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
    let built = Command::new(&cc)
        .arg(&src)
        .arg("-o")
        .arg(&exe)
        .output()
        .unwrap_or_else(|e| panic!("cannot run the C compiler `{cc}` (set $CC): {e}"));
    assert!(
        built.status.success(),
        "compiling against <linux/ppdev.h> failed (install the Linux kernel headers, e.g. linux-libc-dev):\n{}",
        String::from_utf8_lossy(&built.stderr)
    );
    let out = Command::new(&exe).output().unwrap();
    let text = String::from_utf8(out.stdout).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    let get = |name: &str| -> u64 {
        text.lines()
            .find_map(|l| l.strip_prefix(&format!("{name} ")))
            .unwrap_or_else(|| panic!("{name} missing in {text}"))
            .parse()
            .unwrap()
    };
    assert_eq!(ppdev::PPCLAIM, get("PPCLAIM"));
    assert_eq!(ppdev::PPRELEASE, get("PPRELEASE"));
    assert_eq!(ppdev::PPEXCL, get("PPEXCL"));
    assert_eq!(ppdev::PPRSTATUS, get("PPRSTATUS"));
    assert_eq!(ppdev::PPWCONTROL, get("PPWCONTROL"));
    assert_eq!(ppdev::PPWDATA, get("PPWDATA"));
}

#[test]
fn opening_a_missing_port_is_a_clear_error() {
    let e = match ppdev::Ppdev::open(std::path::Path::new("/dev/parport-does-not-exist")) {
        Ok(_) => panic!("opened a port that does not exist"),
        Err(e) => e,
    };
    assert_eq!(e.kind(), std::io::ErrorKind::NotFound);
}
