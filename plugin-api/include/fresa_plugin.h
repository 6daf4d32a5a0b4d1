/*
 * fresa_plugin.h - the Fresa plugin C ABI, version 1.0.
 *
 * Mirrors plugin-api/src/abi.rs exactly; change both together (the tests in
 * plugin-api/tests/c_plugins.rs compare sizes, offsets and constants).
 *
 * A plugin is a shared library (.so / .dylib / .dll) that exports exactly one
 * symbol, `fresa_plugin_v1`, a function returning a pointer to a static
 * FrPluginDescriptor. Build one with, e.g.:
 *
 *     cc -shared -fPIC -I plugin-api/include my.c -o libmy.so
 *
 * Rules of the ABI
 * ----------------
 * Payloads: every request, response, config, event and error that crosses the
 *   boundary is UTF-8 JSON passed as a pointer plus a byte length. Nothing is
 *   NUL-terminated except the three strings of the descriptor. Errors are JSON
 *   objects {"code": "...", "message": "..."}.
 *
 * Ownership: whoever allocates a buffer frees it. Buffers the plugin hands to
 *   the host (the `out_response` of `call`, the `out_error` of `create`) are
 *   copied by the host and then given back through the plugin's own `free`, so
 *   the plugin may use any allocator. Buffers the host passes in (config,
 *   request, and the bytes given to the host table) are only valid for the
 *   duration of that call: copy what you want to keep. The host copies what
 *   you pass to `emit_event` and `log` before they return.
 *
 * Threads: `call` may be invoked concurrently from several host threads on the
 *   same instance (so that stop and feed hold are never stuck behind a slow
 *   request), and may block. The plugin must synchronise its own state. The
 *   host table (FrHost) may be called from any thread, including threads the
 *   plugin started, from `create` until `destroy` returns. `destroy` is called
 *   once, after every `call` on that instance has returned.
 *
 * Errors never unwind: a plugin must never let a C++ exception, a longjmp or
 *   any other non-local exit cross the boundary, in either direction (out of
 *   create/call/destroy/free, or out of a host-table callback it invoked).
 *   Catch everything and return STATUS_ERROR (or STATUS_PANIC for an internal
 *   failure) with a JSON error instead.
 *
 * Versioning: the host refuses a plugin whose abi_major differs from its own,
 *   and a plugin whose abi_minor is newer than its own; it accepts an older or
 *   equal minor. Minor versions only ever append fields to the end of the
 *   structs; `struct_size` says how much is present. It also refuses a plugin
 *   whose target triple names another architecture (first component) or
 *   operating system than its own; see FRESA_TARGET_TRIPLE below.
 *
 * Lifetime: the host never unloads a plugin library, so static data and
 *   threads the plugin starts may outlive every instance.
 */
#ifndef FRESA_PLUGIN_H
#define FRESA_PLUGIN_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ------------------------------------------------------------------------ */
/* Constants                                                                */
/* ------------------------------------------------------------------------ */

/* "FRESAPL1" read as a little-endian uint64_t. Guards against loading an
 * unrelated library that happens to export a symbol of the same name. */
#define FRESA_PLUGIN_MAGIC UINT64_C(0x314C504153455246)

/* The ABI version this header describes. Put these in the descriptor. */
#define FRESA_ABI_MAJOR 1
#define FRESA_ABI_MINOR 0

/* Name of the one exported symbol:
 *     const FrPluginDescriptor *fresa_plugin_v1(void); */
#define FRESA_PLUGIN_SYMBOL "fresa_plugin_v1"

/* Kinds a plugin can provide (bit flags, OR them into `kinds`). */
#define FRESA_KIND_MACHINE_BACKEND UINT32_C(1)
#define FRESA_KIND_PENDANT_TRANSPORT UINT32_C(2)

/* Status codes returned by `create` and `call`. */
/* Success. `call` wrote its JSON answer (or left it empty, meaning {}). */
#define FRESA_STATUS_OK 0
/* The output buffer holds a JSON {"code": ..., "message": ...} error. */
#define FRESA_STATUS_ERROR 1
/* The plugin failed internally (a caught panic/exception); the output buffer
 * holds a JSON error whose "message" says what happened. */
#define FRESA_STATUS_PANIC 2

/* Log levels for FrHost.log. */
#define FRESA_LOG_ERROR UINT32_C(1)
#define FRESA_LOG_WARN UINT32_C(2)
#define FRESA_LOG_INFO UINT32_C(3)
#define FRESA_LOG_DEBUG UINT32_C(4)
#define FRESA_LOG_TRACE UINT32_C(5)

/* ------------------------------------------------------------------------ */
/* Types                                                                    */
/* ------------------------------------------------------------------------ */

/* A byte buffer owned by whoever allocated it. {NULL, 0} is the empty buffer.
 * A buffer the plugin writes into an out-parameter is returned to it, once,
 * through FrPluginDescriptor.free. */
typedef struct FrBuf {
    uint8_t *ptr;
    size_t len;
} FrBuf;

/* Emit one event: a UTF-8 JSON object (for a machine backend, one of the
 * events of the backend contract, e.g. {"event":"alarm","message":"..."}).
 * The host copies the bytes before returning. Callable from any thread. */
typedef void (*FrEmitEventFn)(void *ctx, const uint8_t *json, size_t len);

/* Log one UTF-8 message (not NUL-terminated) at a FRESA_LOG_* level. The host
 * copies the bytes before returning. Callable from any thread. */
typedef void (*FrLogFn)(void *ctx, uint32_t level, const uint8_t *msg, size_t len);

/* Functions the host offers a plugin instance. Valid from `create` until
 * `destroy` returns and callable from any thread. Keep the pointer you get in
 * `create`; do not copy `ctx` out and use it after `destroy`. `ctx` is opaque
 * to the plugin: pass it back as the first argument of every call.
 * `struct_size` is sizeof(FrHost) as the host knows it; newer minor versions
 * may append functions, which a plugin may use only when struct_size covers
 * them. */
typedef struct FrHost {
    size_t struct_size;
    void *ctx;
    FrEmitEventFn emit_event;
    FrLogFn log;
} FrHost;

/* Creates an instance from a JSON config (config_len may be 0, meaning {}).
 * On success writes an opaque, non-NULL `*out_instance` and returns
 * FRESA_STATUS_OK; otherwise writes a JSON error into `*out_error` (freed with
 * `free`) and returns FRESA_STATUS_ERROR or FRESA_STATUS_PANIC. The host
 * initialises `*out_instance` to NULL and `*out_error` to {NULL, 0}. `host`
 * stays valid until `destroy` of this instance returns. */
typedef int32_t (*FrCreateFn)(const FrHost *host, const uint8_t *config, size_t config_len,
                              void **out_instance, FrBuf *out_error);

/* Handles one JSON request and writes the JSON answer, or a JSON error, into
 * `*out_response` (freed with `free`; the host initialises it to {NULL, 0},
 * and an empty answer means {}). May be called concurrently from several
 * threads on the same instance and may block. */
typedef int32_t (*FrCallFn)(void *instance, const uint8_t *request, size_t request_len,
                            FrBuf *out_response);

/* Destroys an instance. Called exactly once, after every `call` on it has
 * returned. After it returns the plugin must not use the host table. */
typedef void (*FrDestroyFn)(void *instance);

/* Frees a buffer this plugin returned. Must accept {NULL, 0}. */
typedef void (*FrFreeFn)(FrBuf buf);

/* What fresa_plugin_v1() returns: a pointer to a static, immutable descriptor.
 * Minor versions may only append fields; set struct_size to
 * sizeof(FrPluginDescriptor). */
typedef struct FrPluginDescriptor {
    uint64_t magic;         /* FRESA_PLUGIN_MAGIC */
    uint16_t abi_major;     /* FRESA_ABI_MAJOR */
    uint16_t abi_minor;     /* FRESA_ABI_MINOR */
    uint32_t struct_size;   /* sizeof(FrPluginDescriptor) */
    /* NUL-terminated target triple the plugin was built for, e.g.
     * "x86_64-unknown-linux-gnu"; FRESA_TARGET_TRIPLE computes it. */
    const char *target;
    /* NUL-terminated plugin name: the `backend` name users configure, e.g.
     * "sim-machine". Must not be empty. */
    const char *name;
    /* NUL-terminated plugin version, e.g. "0.1.0". */
    const char *version;
    /* FRESA_KIND_* bit flags. */
    uint32_t kinds;
    FrCreateFn create;
    FrCallFn call;
    FrDestroyFn destroy;
    FrFreeFn free;
} FrPluginDescriptor;

/* Type of the exported symbol. */
typedef const FrPluginDescriptor *(*FrDescriptorFn)(void);

/* ------------------------------------------------------------------------ */
/* Exporting the descriptor                                                 */
/* ------------------------------------------------------------------------ */

/* Marks a function as exported from the shared library. */
#if defined(_WIN32) || defined(__CYGWIN__)
#define FRESA_PLUGIN_EXPORT __declspec(dllexport)
#elif defined(__GNUC__) || defined(__clang__)
#define FRESA_PLUGIN_EXPORT __attribute__((visibility("default")))
#else
#define FRESA_PLUGIN_EXPORT
#endif

/* The one symbol a plugin defines:
 *
 *     static const FrPluginDescriptor DESCRIPTOR = { FRESA_PLUGIN_MAGIC, ... };
 *     FRESA_PLUGIN_EXPORT const FrPluginDescriptor *fresa_plugin_v1(void) {
 *         return &DESCRIPTOR;
 *     }
 */
FRESA_PLUGIN_EXPORT const FrPluginDescriptor *fresa_plugin_v1(void);

/* ------------------------------------------------------------------------ */
/* FRESA_TARGET_TRIPLE                                                      */
/* ------------------------------------------------------------------------ */

/* FRESA_TARGET_TRIPLE is a string literal naming the platform this file is
 * being compiled for, spelled the way Rust spells target triples (which is
 * what the host compares against), e.g. "x86_64-unknown-linux-gnu",
 * "aarch64-apple-darwin", "x86_64-pc-windows-msvc". Use it for the
 * descriptor's `target` field. The host only compares the architecture (first
 * component) and the operating system, so the vendor and ABI parts do not
 * need to be exact.
 *
 * It is derived from the compiler's predefined macros. On a platform this
 * header does not know it is left undefined: pass it yourself, e.g.
 * -DFRESA_TARGET_TRIPLE='"riscv64gc-unknown-linux-gnu"'. A definition given on
 * the command line always wins. */
#ifndef FRESA_TARGET_TRIPLE

/* Architecture, as the first component of a Rust target triple. */
#if defined(__x86_64__) || defined(__amd64__) || (defined(_M_X64) && !defined(_M_ARM64EC))
#define FRESA_TARGET_ARCH_ "x86_64"
#elif defined(__aarch64__) || defined(_M_ARM64) || defined(_M_ARM64EC)
#define FRESA_TARGET_ARCH_ "aarch64"
#elif defined(__i386__) || defined(_M_IX86)
#define FRESA_TARGET_ARCH_ "i686"
#elif defined(__arm__) || defined(_M_ARM)
#if defined(__ARM_ARCH) && __ARM_ARCH >= 7
#define FRESA_TARGET_ARCH_ "armv7"
#else
#define FRESA_TARGET_ARCH_ "arm"
#endif
#elif defined(__riscv) && defined(__riscv_xlen) && __riscv_xlen == 64
#define FRESA_TARGET_ARCH_ "riscv64gc"
#elif defined(__powerpc64__) && defined(__LITTLE_ENDIAN__)
#define FRESA_TARGET_ARCH_ "powerpc64le"
#elif defined(__s390x__)
#define FRESA_TARGET_ARCH_ "s390x"
#elif defined(__loongarch64)
#define FRESA_TARGET_ARCH_ "loongarch64"
#endif

/* Vendor, operating system and ABI: the rest of the triple. */
#if defined(__ANDROID__)
#if defined(__arm__)
#define FRESA_TARGET_REST_ "-linux-androideabi"
#else
#define FRESA_TARGET_REST_ "-linux-android"
#endif
#elif defined(__linux__)
/* <stdint.h> pulls in <features.h> on glibc, which defines __GLIBC__. */
#if defined(__GLIBC__)
#define FRESA_TARGET_LIBC_ "gnu"
#else
#define FRESA_TARGET_LIBC_ "musl"
#endif
#if defined(__arm__) && defined(__ARM_PCS_VFP)
#define FRESA_TARGET_REST_ "-unknown-linux-" FRESA_TARGET_LIBC_ "eabihf"
#elif defined(__arm__)
#define FRESA_TARGET_REST_ "-unknown-linux-" FRESA_TARGET_LIBC_ "eabi"
#else
#define FRESA_TARGET_REST_ "-unknown-linux-" FRESA_TARGET_LIBC_
#endif
#elif defined(_WIN32)
#if defined(_MSC_VER)
#define FRESA_TARGET_REST_ "-pc-windows-msvc"
#else
#define FRESA_TARGET_REST_ "-pc-windows-gnu"
#endif
#elif defined(__APPLE__) && defined(__MACH__)
#define FRESA_TARGET_REST_ "-apple-darwin"
#elif defined(__FreeBSD__)
#define FRESA_TARGET_REST_ "-unknown-freebsd"
#elif defined(__NetBSD__)
#define FRESA_TARGET_REST_ "-unknown-netbsd"
#elif defined(__OpenBSD__)
#define FRESA_TARGET_REST_ "-unknown-openbsd"
#endif

#if defined(FRESA_TARGET_ARCH_) && defined(FRESA_TARGET_REST_)
/* Two adjacent string literals: the compiler joins them into one. */
#define FRESA_TARGET_TRIPLE FRESA_TARGET_ARCH_ FRESA_TARGET_REST_
#endif

#endif /* FRESA_TARGET_TRIPLE */

#ifdef __cplusplus
} /* extern "C" */
#endif

#endif /* FRESA_PLUGIN_H */
