/*
 * Reports the layout and constants of include/fresa_plugin.h as the C compiler
 * sees them, so tests/c_plugins.rs can compare them with src/abi.rs.
 */
#include "fresa_plugin.h"

#include <stddef.h>

#define FIELD(T, f) offsetof(T, f)

static const uint64_t LAYOUT[] = {
    sizeof(FrBuf),
    _Alignof(FrBuf),
    FIELD(FrBuf, ptr),
    FIELD(FrBuf, len),

    sizeof(FrHost),
    _Alignof(FrHost),
    FIELD(FrHost, struct_size),
    FIELD(FrHost, ctx),
    FIELD(FrHost, emit_event),
    FIELD(FrHost, log),

    sizeof(FrPluginDescriptor),
    _Alignof(FrPluginDescriptor),
    FIELD(FrPluginDescriptor, magic),
    FIELD(FrPluginDescriptor, abi_major),
    FIELD(FrPluginDescriptor, abi_minor),
    FIELD(FrPluginDescriptor, struct_size),
    FIELD(FrPluginDescriptor, target),
    FIELD(FrPluginDescriptor, name),
    FIELD(FrPluginDescriptor, version),
    FIELD(FrPluginDescriptor, kinds),
    FIELD(FrPluginDescriptor, create),
    FIELD(FrPluginDescriptor, call),
    FIELD(FrPluginDescriptor, destroy),
    FIELD(FrPluginDescriptor, free),

    FRESA_PLUGIN_MAGIC,
    FRESA_ABI_MAJOR,
    FRESA_ABI_MINOR,
    FRESA_KIND_MACHINE_BACKEND,
    FRESA_KIND_PENDANT_TRANSPORT,
    (uint64_t)FRESA_STATUS_OK,
    (uint64_t)FRESA_STATUS_ERROR,
    (uint64_t)FRESA_STATUS_PANIC,
    FRESA_LOG_ERROR,
    FRESA_LOG_WARN,
    FRESA_LOG_INFO,
    FRESA_LOG_DEBUG,
    FRESA_LOG_TRACE,
};

FRESA_PLUGIN_EXPORT const uint64_t *fresa_layout(size_t *count);
FRESA_PLUGIN_EXPORT const uint64_t *fresa_layout(size_t *count) {
    *count = sizeof LAYOUT / sizeof LAYOUT[0];
    return LAYOUT;
}

FRESA_PLUGIN_EXPORT const char *fresa_symbol(void);
FRESA_PLUGIN_EXPORT const char *fresa_symbol(void) { return FRESA_PLUGIN_SYMBOL; }

FRESA_PLUGIN_EXPORT const char *fresa_target(void);
FRESA_PLUGIN_EXPORT const char *fresa_target(void) { return FRESA_TARGET_TRIPLE; }

/* The function-pointer typedefs must accept functions of the documented shape. */
static int32_t c(const FrHost *h, const uint8_t *p, size_t n, void **o, FrBuf *e) {
    (void)h; (void)p; (void)n; (void)o; (void)e;
    return FRESA_STATUS_OK;
}
static int32_t k(void *i, const uint8_t *p, size_t n, FrBuf *o) {
    (void)i; (void)p; (void)n; (void)o;
    return FRESA_STATUS_OK;
}
static void d(void *i) { (void)i; }
static void f(FrBuf b) { (void)b; }
static void ev(void *ctx, const uint8_t *j, size_t n) { (void)ctx; (void)j; (void)n; }
static void lg(void *ctx, uint32_t l, const uint8_t *m, size_t n) { (void)ctx; (void)l; (void)m; (void)n; }

static const FrPluginDescriptor *desc(void) { return NULL; }

/* Compiled with -Werror: an incompatible typedef fails the build. */
FRESA_PLUGIN_EXPORT int fresa_typedefs_ok(void);
FRESA_PLUGIN_EXPORT int fresa_typedefs_ok(void) {
    FrCreateFn cf = c;
    FrCallFn kf = k;
    FrDestroyFn df = d;
    FrFreeFn ff = f;
    FrEmitEventFn ef = ev;
    FrLogFn lf = lg;
    FrDescriptorFn g = desc;
    (void)cf; (void)kf; (void)df; (void)ff; (void)ef; (void)lf; (void)g;
    return 1;
}
