/* CRC-16/CCITT-FALSE, COBS and framing: round trips, and everything the receiver must reject. */
#include <string.h>

#include "check.h"
#include "cobs.h"
#include "crc16.h"
#include "frame.h"

static void crc_matches_the_catalogue_check_value(void)
{
    const uint8_t text[] = "123456789";
    CHECK(crc16_ccitt(text, 9) == 0x29B1);
    CHECK(crc16_ccitt(text, 0) == 0xFFFF); /* the init value, nothing folded in */
}

static void cobs_round_trip(const uint8_t *data, size_t len)
{
    uint8_t encoded[COBS_ENCODED_MAX(1100)];
    uint8_t decoded[1100];
    size_t encoded_len = cobs_encode(data, len, encoded, sizeof encoded);
    CHECK(encoded_len > len);
    CHECK(memchr(encoded, 0, encoded_len) == NULL); /* the delimiter never occurs inside */
    size_t decoded_len = 0;
    CHECK(cobs_decode(encoded, encoded_len, decoded, sizeof decoded, &decoded_len));
    CHECK(decoded_len == len && memcmp(decoded, data, len) == 0);
}

static void cobs_round_trips_zeros_and_long_runs(void)
{
    uint8_t data[1000];
    memset(data, 0, sizeof data);
    cobs_round_trip(data, 0);
    cobs_round_trip(data, 1);
    cobs_round_trip(data, 300); /* nothing but zeros */
    size_t lengths[] = {1, 253, 254, 255, 508, 600, 1000}; /* around the 254-byte block boundary */
    for (size_t k = 0; k < sizeof lengths / sizeof lengths[0]; k++) {
        for (size_t i = 0; i < lengths[k]; i++) {
            data[i] = (uint8_t)(1 + i % 255); /* no zeros */
        }
        cobs_round_trip(data, lengths[k]);
        data[lengths[k] / 2] = 0;
        cobs_round_trip(data, lengths[k]);
    }
    uint32_t x = 12345; /* a fixed pseudo-random mix */
    for (size_t i = 0; i < sizeof data; i++) {
        x = x * 1103515245u + 12345u;
        data[i] = (uint8_t)((x >> 16) % 4 == 0 ? 0 : x >> 16);
    }
    cobs_round_trip(data, sizeof data);
}

static void cobs_rejects_zeros_and_blocks_past_the_end(void)
{
    uint8_t out[16];
    size_t len = 0;
    const uint8_t zero_code[] = {0x02, 0x11, 0x00, 0x11};
    const uint8_t zero_inside[] = {0x03, 0x11, 0x00};
    const uint8_t past_end[] = {0x05, 0x11, 0x22};
    CHECK(!cobs_decode(zero_code, sizeof zero_code, out, sizeof out, &len));
    CHECK(!cobs_decode(zero_inside, sizeof zero_inside, out, sizeof out, &len));
    CHECK(!cobs_decode(past_end, sizeof past_end, out, sizeof out, &len));
    const uint8_t too_big[] = {0x04, 1, 2, 3};
    CHECK(!cobs_decode(too_big, sizeof too_big, out, 2, &len));
}

/* Push every byte; the result of the last non-NONE push, and the frame it produced. */
static frame_result push_all(frame_rx *rx, const uint8_t *wire, size_t len, frame_msg *msg, int *invalid)
{
    frame_result last = FRAME_NONE;
    for (size_t i = 0; i < len; i++) {
        frame_result r = frame_rx_push(rx, wire[i], msg);
        if (r == FRAME_INVALID) {
            (*invalid)++;
        }
        if (r != FRAME_NONE) {
            last = r;
        }
    }
    return last;
}

static void frames_round_trip(void)
{
    const uint8_t payload[] = {0x00, 0x30, 0x00, 0xFF, 0x01};
    uint8_t wire[64];
    size_t len = frame_encode(0x02, 0x0201, payload, sizeof payload, wire, sizeof wire);
    CHECK(len > 0 && wire[len - 1] == 0 && memchr(wire, 0, len - 1) == NULL);
    frame_rx rx;
    frame_rx_init(&rx);
    frame_msg msg;
    int invalid = 0;
    CHECK(push_all(&rx, wire, len, &msg, &invalid) == FRAME_OK && invalid == 0);
    CHECK(msg.type == 0x02 && msg.seq == 0x0201 && msg.payload_len == sizeof payload);
    CHECK(memcmp(msg.payload, payload, sizeof payload) == 0);
}

static void frames_with_a_bad_crc_or_too_short_are_invalid(void)
{
    uint8_t wire[64];
    size_t len = frame_encode(0x05, 7, NULL, 0, wire, sizeof wire);
    frame_rx rx;
    frame_rx_init(&rx);
    frame_msg msg;
    int invalid = 0;
    wire[2] ^= 0x10; /* one flipped bit in the seq */
    CHECK(push_all(&rx, wire, len, &msg, &invalid) == FRAME_INVALID && invalid == 1);
    const uint8_t short_frame[] = {0x05, 0x05, 0x07, 0x01, 0x12, 0x00}; /* 4 bytes decoded */
    invalid = 0;
    CHECK(push_all(&rx, short_frame, sizeof short_frame, &msg, &invalid) == FRAME_INVALID && invalid == 1);
    const uint8_t empty[] = {0x00, 0x00}; /* delimiters only: no frame, no error */
    invalid = 0;
    CHECK(push_all(&rx, empty, sizeof empty, &msg, &invalid) == FRAME_NONE && invalid == 0);
}

static void an_overlong_run_is_dropped_once_and_the_next_frame_decodes(void)
{
    frame_rx rx;
    frame_rx_init(&rx);
    frame_msg msg;
    int invalid = 0;
    uint8_t noise[1500];
    memset(noise, 0x55, sizeof noise);
    CHECK(push_all(&rx, noise, sizeof noise, &msg, &invalid) == FRAME_INVALID && invalid == 1);
    uint8_t wire[64];
    size_t len = frame_encode(0x05, 9, NULL, 0, wire, sizeof wire);
    invalid = 0;
    /* The frame's own delimiter ends the overlong run first: the frame after that one decodes. */
    CHECK(push_all(&rx, wire, len, &msg, &invalid) == FRAME_NONE && invalid == 0);
    CHECK(push_all(&rx, wire, len, &msg, &invalid) == FRAME_OK && msg.seq == 9);
    /* Exactly 1024 bytes is still a frame's length (invalid here only for its CRC). */
    invalid = 0;
    push_all(&rx, noise, FRAME_MAX_WIRE_BYTES, &msg, &invalid);
    CHECK(invalid == 0);
}

void run_wire_tests(void)
{
    RUN_TEST(crc_matches_the_catalogue_check_value);
    RUN_TEST(cobs_round_trips_zeros_and_long_runs);
    RUN_TEST(cobs_rejects_zeros_and_blocks_past_the_end);
    RUN_TEST(frames_round_trip);
    RUN_TEST(frames_with_a_bad_crc_or_too_short_are_invalid);
    RUN_TEST(an_overlong_run_is_dropped_once_and_the_next_frame_decodes);
}
