/* arena_proto: framing of the arena robot wire protocol (see docs/robot-protocol.md).
 *
 * Plain C99, no allocation, no Arduino dependencies, so the same file is compiled
 * into the Zumo 32U4 sketch and into a host shared library that the Python tests
 * (tests/robot_bridge/test_bridge_firmware_c.py) check against arena/robot_protocol.py.
 *
 * Packet = header (8 B, little-endian: version u8, type u8, seq u16, time_us u32)
 *        + body + CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of header+body, LE.
 * Frame  = COBS(packet) followed by one 0x00 delimiter.
 */
#ifndef ARENA_PROTO_H
#define ARENA_PROTO_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define AP_VERSION 1
#define AP_HEADER_SIZE 8
#define AP_MAX_PACKET 64
#define AP_MAX_FRAME (AP_MAX_PACKET + 2) /* COBS overhead (1) + delimiter (1) */
#define AP_MAX_RAW (AP_MAX_PACKET + 1)   /* COBS bytes of the largest packet */

#define AP_HELLO 0x01
#define AP_HELLO_REPLY 0x02
#define AP_SET_MOTORS 0x10
#define AP_SET_LED 0x11
#define AP_STOP 0x12
#define AP_TELEMETRY 0x20
#define AP_PING 0x30
#define AP_PONG 0x31
#define AP_ERROR 0x7F

#define AP_ERR_BAD_VERSION 1
#define AP_ERR_UNKNOWN_TYPE 2
#define AP_ERR_BAD_LENGTH 3
#define AP_ERR_BAD_VALUE 4

/* Decoder results of ap_decoder_feed(). */
#define AP_NONE 0       /* byte consumed, no frame yet */
#define AP_FRAME 1      /* a valid packet is in dec->packet (dec->len bytes) */
#define AP_BAD_CRC -1
#define AP_BAD_FRAME -2 /* bad COBS, too short or too long */
#define AP_BAD_VERSION -3

uint16_t ap_crc16(const uint8_t *data, size_t len);
/* COBS-encode len bytes into out (room for len + len/254 + 1); returns the output length. */
size_t ap_cobs_encode(const uint8_t *in, size_t len, uint8_t *out);
/* COBS-decode; returns the output length, or (size_t)-1 on a malformed input. */
size_t ap_cobs_decode(const uint8_t *in, size_t len, uint8_t *out);
/* Build a full frame (COBS + 0x00) into out (>= AP_MAX_FRAME bytes); returns its length, 0 if body too long. */
size_t ap_encode_frame(uint8_t type, uint16_t seq, uint32_t time_us,
                       const uint8_t *body, size_t body_len, uint8_t *out);

typedef struct {
  uint8_t raw[AP_MAX_RAW];
  uint8_t packet[AP_MAX_RAW];
  size_t raw_len;
  size_t len;        /* packet length after AP_FRAME */
  uint8_t overflow;
  uint32_t frames, crc_errors, frame_errors, version_errors;
} ap_decoder;

void ap_decoder_init(ap_decoder *dec);
/* Feed one byte; returns AP_NONE, AP_FRAME or a negative AP_BAD_* code (counted). */
int ap_decoder_feed(ap_decoder *dec, uint8_t byte);

/* Header accessors of a decoded packet. */
static inline uint8_t ap_type(const uint8_t *p) { return p[1]; }
static inline uint16_t ap_seq(const uint8_t *p) { return (uint16_t)(p[2] | (p[3] << 8)); }
static inline uint32_t ap_time(const uint8_t *p) {
  return (uint32_t)p[4] | ((uint32_t)p[5] << 8) | ((uint32_t)p[6] << 16) | ((uint32_t)p[7] << 24);
}

/* Little-endian helpers for bodies. */
static inline void ap_put_u16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static inline void ap_put_u32(uint8_t *p, uint32_t v) {
  p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);
}
static inline int16_t ap_get_i16(const uint8_t *p) { return (int16_t)(uint16_t)(p[0] | (p[1] << 8)); }

#ifdef __cplusplus
}
#endif
#endif
