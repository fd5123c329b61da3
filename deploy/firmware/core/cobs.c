#include "cobs.h"

size_t cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t out_cap)
{
    if (out_cap < COBS_ENCODED_MAX(len)) {
        return 0;
    }
    size_t code_at = 0; /* where the current block's code byte goes, filled in when the block ends */
    size_t out_len = 1;
    uint8_t code = 1; /* 1 + data bytes in the current block */
    for (size_t i = 0; i < len; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = out_len++;
            code = 1;
            continue;
        }
        out[out_len++] = in[i];
        code++;
        if (code == 0xFF) { /* a full block of 254 non-zero bytes: it implies no zero after it */
            out[code_at] = code;
            code_at = out_len++;
            code = 1;
        }
    }
    out[code_at] = code;
    return out_len;
}

bool cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t out_cap, size_t *out_len)
{
    size_t n = 0;
    size_t i = 0;
    while (i < len) {
        uint8_t code = in[i];
        if (code == 0 || i + code > len + 1) { /* a zero, or a block running past the end */
            return false;
        }
        size_t data_len = (size_t)code - 1;
        if (n + data_len > out_cap) {
            return false;
        }
        for (size_t k = 0; k < data_len; k++) {
            if (in[i + 1 + k] == 0) {
                return false;
            }
            out[n++] = in[i + 1 + k];
        }
        i += code;
        /* A block shorter than 254 bytes stood for a zero after it, except at the very end. */
        if (code < 0xFF && i < len) {
            if (n >= out_cap) {
                return false;
            }
            out[n++] = 0;
        }
    }
    *out_len = n;
    return true;
}
