// A plugin written in C++: the header's extern "C" block keeps `fresa_plugin_v1`
// unmangled, and every entry point catches exceptions so none crosses the
// boundary (an exception becomes FRESA_STATUS_PANIC with a JSON error).
#include "fresa_plugin.h"

#include <cstdlib>
#include <cstring>
#include <new>
#include <stdexcept>
#include <string>

namespace {

struct Instance {
    const FrHost *host;
};

FrBuf to_buf(const std::string &s) {
    FrBuf b = {nullptr, 0};
    b.ptr = static_cast<uint8_t *>(std::malloc(s.size() + 1));
    if (b.ptr != nullptr) {
        std::memcpy(b.ptr, s.data(), s.size());
        b.len = s.size();
    }
    return b;
}

std::string error_json(const char *code, const std::string &message) {
    // Messages here contain no characters that need JSON escaping.
    return std::string("{\"code\":\"") + code + "\",\"message\":\"" + message + "\"}";
}

int32_t create(const FrHost *host, const uint8_t *, size_t, void **out_instance,
               FrBuf *out_error) {
    try {
        *out_instance = new Instance{host};
        return FRESA_STATUS_OK;
    } catch (const std::exception &e) {
        *out_error = to_buf(error_json("exception", e.what()));
        return FRESA_STATUS_PANIC;
    }
}

std::string handle(const std::string &request) {
    if (request.find("\"op\":\"throw\"") != std::string::npos) {
        throw std::runtime_error("thrown on purpose");
    }
    return "{\"ok\":true}";
}

int32_t call(void *, const uint8_t *request, size_t request_len, FrBuf *out_response) {
    try {
        std::string req(reinterpret_cast<const char *>(request), request_len);
        *out_response = to_buf(handle(req));
        return FRESA_STATUS_OK;
    } catch (const std::exception &e) {
        *out_response = to_buf(error_json("exception", e.what()));
        return FRESA_STATUS_PANIC;
    } catch (...) {
        *out_response = to_buf(error_json("exception", "unknown exception"));
        return FRESA_STATUS_PANIC;
    }
}

void destroy(void *instance) { delete static_cast<Instance *>(instance); }

void free_buf(FrBuf buf) { std::free(buf.ptr); }

const FrPluginDescriptor DESCRIPTOR = {
    FRESA_PLUGIN_MAGIC,
    FRESA_ABI_MAJOR,
    FRESA_ABI_MINOR,
    sizeof(FrPluginDescriptor),
    FRESA_TARGET_TRIPLE,
    "cxx-plugin",
    "1.0.0",
    FRESA_KIND_MACHINE_BACKEND,
    create,
    call,
    destroy,
    free_buf,
};

}  // namespace

const FrPluginDescriptor *fresa_plugin_v1(void) { return &DESCRIPTOR; }
