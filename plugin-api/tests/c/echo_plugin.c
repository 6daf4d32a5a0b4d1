/*
 * A tiny machine backend written in C against include/fresa_plugin.h, used by
 * tests/c_plugins.rs. It echoes every request back, emits an event and a log
 * line through the host table on each call, and counts what it allocates and
 * destroys so the test can check that the host honours the ownership rules.
 *
 * Descriptor fields can be overridden with -D to build broken variants:
 *   PLUGIN_MAGIC, PLUGIN_ABI_MAJOR, PLUGIN_ABI_MINOR, PLUGIN_STRUCT_SIZE,
 *   PLUGIN_TARGET, PLUGIN_NAME; NO_DESCRIPTOR leaves fresa_plugin_v1 out;
 *   HEAD_ONLY makes it return just the 16-byte head of a descriptor.
 */
#include "fresa_plugin.h"

#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifndef PLUGIN_MAGIC
#define PLUGIN_MAGIC FRESA_PLUGIN_MAGIC
#endif
#ifndef PLUGIN_ABI_MAJOR
#define PLUGIN_ABI_MAJOR FRESA_ABI_MAJOR
#endif
#ifndef PLUGIN_ABI_MINOR
#define PLUGIN_ABI_MINOR FRESA_ABI_MINOR
#endif
#ifndef PLUGIN_STRUCT_SIZE
#define PLUGIN_STRUCT_SIZE sizeof(FrPluginDescriptor)
#endif
#ifndef PLUGIN_TARGET
#define PLUGIN_TARGET FRESA_TARGET_TRIPLE
#endif
#ifndef PLUGIN_NAME
#define PLUGIN_NAME "c-echo"
#endif

/* Observability for the test (exported, read through dlsym). */
static atomic_long live_buffers;  /* allocated by us, not yet given back to free */
static atomic_long live_instances;
static atomic_long destroyed;
static atomic_long seen_host_struct_size;

FRESA_PLUGIN_EXPORT long echo_live_buffers(void) { return atomic_load(&live_buffers); }
FRESA_PLUGIN_EXPORT long echo_live_instances(void) { return atomic_load(&live_instances); }
FRESA_PLUGIN_EXPORT long echo_destroyed(void) { return atomic_load(&destroyed); }
FRESA_PLUGIN_EXPORT long echo_host_struct_size(void) { return atomic_load(&seen_host_struct_size); }

typedef struct Echo {
    const FrHost *host;
    atomic_long calls;
} Echo;

static int contains(const uint8_t *hay, size_t len, const char *needle) {
    size_t n = strlen(needle);
    if (hay == NULL || n > len) {
        return 0;
    }
    for (size_t i = 0; i + n <= len; i++) {
        if (memcmp(hay + i, needle, n) == 0) {
            return 1;
        }
    }
    return 0;
}

/* Copies `s` into a buffer that goes back through echo_free. */
static FrBuf make_buf(const char *s, size_t len) {
    FrBuf b = {NULL, 0};
    b.ptr = (uint8_t *)malloc(len == 0 ? 1 : len);
    if (b.ptr == NULL) {
        return b;
    }
    memcpy(b.ptr, s, len);
    b.len = len;
    atomic_fetch_add(&live_buffers, 1);
    return b;
}

static FrBuf make_str(const char *s) { return make_buf(s, strlen(s)); }

static int32_t echo_create(const FrHost *host, const uint8_t *config, size_t config_len,
                           void **out_instance, FrBuf *out_error) {
    atomic_store(&seen_host_struct_size, (long)host->struct_size);
    if (contains(config, config_len, "\"fail_create\"")) {
        *out_error = make_str("{\"code\":\"bad_config\",\"message\":\"create refused: fail_create is set\"}");
        return FRESA_STATUS_ERROR;
    }
    Echo *e = (Echo *)calloc(1, sizeof(Echo));
    if (e == NULL) {
        *out_error = make_str("{\"code\":\"oom\",\"message\":\"out of memory\"}");
        return FRESA_STATUS_PANIC;
    }
    e->host = host;
    atomic_init(&e->calls, 0);
    atomic_fetch_add(&live_instances, 1);
    *out_instance = e;
    return FRESA_STATUS_OK;
}

static int32_t echo_call(void *instance, const uint8_t *request, size_t request_len,
                         FrBuf *out_response) {
    Echo *e = (Echo *)instance;
    long n = atomic_fetch_add(&e->calls, 1) + 1;

    char line[128];
    int k = snprintf(line, sizeof line, "echo call %ld", n);
    e->host->log(e->host->ctx, FRESA_LOG_INFO, (const uint8_t *)line, (size_t)k);
    k = snprintf(line, sizeof line, "{\"event\":\"echoed\",\"call\":%ld}", n);
    e->host->emit_event(e->host->ctx, (const uint8_t *)line, (size_t)k);

    if (contains(request, request_len, "\"op\":\"fail\"")) {
        *out_response = make_str("{\"code\":\"echo_failed\",\"message\":\"asked to fail\"}");
        return FRESA_STATUS_ERROR;
    }
    if (contains(request, request_len, "\"op\":\"bogus_status\"")) {
        *out_response = make_str("{}");
        return 42;
    }
    if (contains(request, request_len, "\"op\":\"empty\"")) {
        return FRESA_STATUS_OK; /* leaves the answer empty: means {} */
    }

    /* {"echo":<request>,"call":n} */
    const char *head = "{\"echo\":";
    char tail[64];
    int t = snprintf(tail, sizeof tail, ",\"call\":%ld}", n);
    size_t len = strlen(head) + request_len + (size_t)t;
    char *out = (char *)malloc(len);
    if (out == NULL) {
        *out_response = make_str("{\"code\":\"oom\",\"message\":\"out of memory\"}");
        return FRESA_STATUS_PANIC;
    }
    memcpy(out, head, strlen(head));
    memcpy(out + strlen(head), request, request_len);
    memcpy(out + strlen(head) + request_len, tail, (size_t)t);
    *out_response = make_buf(out, len);
    free(out);
    return FRESA_STATUS_OK;
}

static void echo_destroy(void *instance) {
    free(instance);
    atomic_fetch_sub(&live_instances, 1);
    atomic_fetch_add(&destroyed, 1);
}

static void echo_free(FrBuf buf) {
    if (buf.ptr == NULL) {
        return;
    }
    free(buf.ptr);
    atomic_fetch_sub(&live_buffers, 1);
}

static const FrPluginDescriptor DESCRIPTOR = {
    PLUGIN_MAGIC,
    PLUGIN_ABI_MAJOR,
    PLUGIN_ABI_MINOR,
    (uint32_t)(PLUGIN_STRUCT_SIZE),
    PLUGIN_TARGET,
    PLUGIN_NAME,
    "0.3.1",
    FRESA_KIND_MACHINE_BACKEND | FRESA_KIND_PENDANT_TRANSPORT,
    echo_create,
    echo_call,
    echo_destroy,
    echo_free,
};

#if defined(NO_DESCRIPTOR)
/* Looks plausible, but is not the symbol the host looks for. */
FRESA_PLUGIN_EXPORT const FrPluginDescriptor *fresa_plugin_v0(void);
FRESA_PLUGIN_EXPORT const FrPluginDescriptor *fresa_plugin_v0(void) { return &DESCRIPTOR; }
#elif defined(HEAD_ONLY)
/* Only the fixed head of a descriptor, as a truncated or foreign library might have. */
struct Head {
    uint64_t magic;
    uint16_t abi_major;
    uint16_t abi_minor;
    uint32_t struct_size;
};
static const struct Head HEAD = {FRESA_PLUGIN_MAGIC, FRESA_ABI_MAJOR, FRESA_ABI_MINOR,
                                 sizeof(struct Head)};
FRESA_PLUGIN_EXPORT const FrPluginDescriptor *fresa_plugin_v0(void);
FRESA_PLUGIN_EXPORT const FrPluginDescriptor *fresa_plugin_v0(void) { return &DESCRIPTOR; }
FRESA_PLUGIN_EXPORT const FrPluginDescriptor *fresa_plugin_v1(void) {
    return (const FrPluginDescriptor *)(const void *)&HEAD;
}
#else
FRESA_PLUGIN_EXPORT const FrPluginDescriptor *fresa_plugin_v1(void) { return &DESCRIPTOR; }
#endif
