/* Frames of docs/device-protocol.md: line assembly, decoding a command, building replies
 * and events. No I/O and no heap: every buffer is inside the structs. */
#ifndef ML_FRAME_H
#define ML_FRAME_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define FRAME_MAX_BYTES 256 /* longest line, terminator included */
#define FRAME_MAX_FIELDS 24

/* ---- receiving ---------------------------------------------------------------------- */

typedef struct {
    char buf[FRAME_MAX_BYTES + 1];
    size_t len;
    bool overflowed; /* line grew past the limit: discard the rest of it silently */
} line_rx_t;

typedef enum {
    LINE_NONE,     /* need more bytes */
    LINE_READY,    /* buf holds one line without its '\n' (NUL-terminated), len set */
    LINE_OVERFLOW, /* a line passed FRAME_MAX_BYTES: garbage (reported once per line) */
} line_status_t;

void line_rx_reset(line_rx_t *rx);
/* Feed one byte. After LINE_READY the caller consumes buf, then calls line_rx_reset(). */
line_status_t line_rx_push(line_rx_t *rx, uint8_t byte);

typedef struct {
    const char *key;
    const char *value;
} field_t;

typedef struct {
    char body[FRAME_MAX_BYTES + 1]; /* tokens, split in place */
    uint16_t seq;
    const char *name;
    field_t fields[FRAME_MAX_FIELDS];
    int n_fields;
} command_t;

/* Decode one line (no '\n'; a trailing '\r' is tolerated) as a host command. Returns NULL on
 * success or a short reason: anything that is not a valid *command* frame is garbage to the
 * device (bad checksum, bad tokens, a reply or an event). */
const char *frame_decode_command(const char *line, size_t len, command_t *out);

/* The value of field `key`, or NULL. */
const char *command_field(const command_t *cmd, const char *key);

/* ---- sending ------------------------------------------------------------------------ */

typedef struct {
    char buf[FRAME_MAX_BYTES + 1];
    size_t len;
    bool overflow;
    bool reply;   /* a reply (seq below) rather than an event: what to send if it overflows */
    uint16_t seq; /* the reply's sequence number */
} frame_tx_t;

void frame_begin_reply(frame_tx_t *f, uint16_t seq, bool ok);
void frame_begin_event(frame_tx_t *f, uint16_t number, const char *name);
void frame_add_text(frame_tx_t *f, const char *text);            /* " text" (ERR code, words) */
void frame_add_str(frame_tx_t *f, const char *key, const char *value);
void frame_add_int(frame_tx_t *f, const char *key, int64_t value);
void frame_add_micro(frame_tx_t *f, const char *key, int64_t micro); /* µ-units as decimal */
void frame_add_micro_list(frame_tx_t *f, const char *key, const int64_t *micro, int n);
/* Appends "*CCCC\n"; returns the frame length (0 if it would not fit: never sent). */
size_t frame_finish(frame_tx_t *f);

#endif
