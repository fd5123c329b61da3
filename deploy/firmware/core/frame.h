/* Frames on the wire: COBS(type u8 | seq u16 LE | payload | crc16 LE) followed by a 0x00 delimiter. */
#ifndef CLOTHD_FW_FRAME_H
#define CLOTHD_FW_FRAME_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define FRAME_MAX_WIRE_BYTES 1024 /* a longer run without a delimiter is noise, dropped whole */
#define FRAME_HEADER_BYTES 3      /* type, seq */
#define FRAME_CRC_BYTES 2
#define FRAME_MIN_DECODED_BYTES (FRAME_HEADER_BYTES + FRAME_CRC_BYTES)

typedef struct {
    uint8_t type;
    uint16_t seq;
    const uint8_t *payload; /* points into the receiver's buffer: valid until the next byte is pushed */
    size_t payload_len;
} frame_msg;

typedef enum {
    FRAME_NONE,    /* nothing complete yet (or an empty frame between two delimiters) */
    FRAME_OK,      /* *msg holds a frame with a good CRC */
    FRAME_INVALID, /* bad COBS, short, bad CRC, or a run past FRAME_MAX_WIRE_BYTES */
} frame_result;

/* The receiver: collects bytes up to the next delimiter. Lives in static storage (no allocation). */
typedef struct {
    uint8_t wire[FRAME_MAX_WIRE_BYTES];
    size_t wire_len;
    bool overflowed; /* discarding until the next delimiter */
    uint8_t decoded[FRAME_MAX_WIRE_BYTES];
} frame_rx;

void frame_rx_init(frame_rx *rx);

/* Feed one received byte; on FRAME_OK, *msg is the frame that byte completed. */
frame_result frame_rx_push(frame_rx *rx, uint8_t byte, frame_msg *msg);

/* Encode one frame with its delimiter into out; returns the wire length, or 0 when out_cap is too small. */
size_t frame_encode(uint8_t type, uint16_t seq, const uint8_t *payload, size_t payload_len, uint8_t *out,
                    size_t out_cap);

#endif
