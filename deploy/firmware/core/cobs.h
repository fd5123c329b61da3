#ifndef CLOTHD_FW_COBS_H
#define CLOTHD_FW_COBS_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* The most bytes cobs_encode() can write for len input bytes: one code byte per 254 data bytes, plus one. */
#define COBS_ENCODED_MAX(len) ((len) + (len) / 254 + 1)

/* Consistent Overhead Byte Stuffing: writes len bytes without any zero to out (no delimiter appended).
 * Returns the encoded length, or 0 when out_cap is too small. */
size_t cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t out_cap);

/* Undoes cobs_encode(). False when the input is not valid COBS (a zero byte, a block running past the
 * end) or the result does not fit out_cap. */
bool cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t out_cap, size_t *out_len);

#endif
